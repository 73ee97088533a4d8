"""The fitted field as a surface: where the training views' rays end, the mesh, the ground, alignment to the views'
colours and the baked texture."""
