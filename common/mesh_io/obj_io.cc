// placeholder until the obj reader lands
