"""Offline tools that derive or check the geometry.

- :mod:`.capsule_fit`: the capsule fit of the collision meshes (``python -m mjx_multiarm.reference.capsule_fit``).
- :mod:`.mesh_reference`: exact triangle-mesh distances of the UR5 meshes (needs ``coal``).
"""
