// placeholder until the vtk_legacy reader lands
