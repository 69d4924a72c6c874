// placeholder until the stl reader lands
