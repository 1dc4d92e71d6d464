"""Bakes: one parameter setting of a model as a brick grid that a browser marches
(``bake_file`` the format, ``baking`` the bake, ``bake_render`` the CPU reference renderer)."""
