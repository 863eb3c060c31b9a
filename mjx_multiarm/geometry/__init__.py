"""The arm and its scene: UR5 model, transforms, kinematics, the padded scene, the collision
kernel, inverse kinematics, and the numpy entry point :func:`evaluate.evaluate_arms`.
"""
