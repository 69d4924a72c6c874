// placeholder until the tetgen reader lands
