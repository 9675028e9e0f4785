"""Maps from a run: a ROS ``map_server`` occupancy grid by ray casting (2D), the same grid from the trained M-Net,
an OctoMap ``.bt`` (3D, optional ``pyoctomap``), the M-Net's decision surface as a mesh, and a Rerun recording
(optional ``rerun-sdk``). :func:`dm2_backend.maps.run_maps.write_run_maps` writes them into a run folder."""
