// placeholder until the gmsh reader lands
