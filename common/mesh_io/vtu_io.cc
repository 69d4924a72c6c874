// placeholder until the vtu reader lands
