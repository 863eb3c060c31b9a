"""Offline tools that derive or check the geometry: the capsule fit of the collision meshes
(``python -m mjx_multiarm.reference.capsule_fit``) and exact mesh distances (needs ``coal``).
"""
