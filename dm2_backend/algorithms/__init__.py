"""The algorithms the plugins are built from: point clouds and scale (``common``), 2D/3D ICP (``icp``),
correlative scan matching (``correlative``), the gates that accept a registration (``gates``), keyframe submaps
(``keyframes``), loop-closure pose graphs (``loop_graph``, ``loop_graph3d``), Scan Context descriptors
(``scan_context``) and the checks shared by the place-recognition plugins (``topology``).

Plugins (``plugins/``), baselines and the preparation import these; nothing imports a plugin module except the
plugin registry.
"""
