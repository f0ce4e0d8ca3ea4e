"""Pure array functions shared by models, sensors and observers. Every function broadcasts over
leading batch axes; the last axis (or last two, for matrices) is the object itself."""

from needlecli.numerics.angles import angle_diff, sincos, wrap_angle
from needlecli.numerics.integrate import complex_step_jacobian, finite_difference_jacobian, rk4_step
from needlecli.numerics.rotations import (
    euler_xyz_to_matrix,
    hat,
    matrix_to_euler_xyz,
    matrix_to_quaternion,
    project_to_so3,
    quaternion_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    so3_exp,
    so3_log,
    vee,
)

__all__ = [
    "wrap_angle",
    "angle_diff",
    "sincos",
    "rk4_step",
    "complex_step_jacobian",
    "finite_difference_jacobian",
    "hat",
    "vee",
    "rot_x",
    "rot_y",
    "rot_z",
    "euler_xyz_to_matrix",
    "matrix_to_euler_xyz",
    "so3_exp",
    "so3_log",
    "rotation_angle",
    "project_to_so3",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
]
