"""Pure array functions shared by models, sensors and observers. Every function broadcasts over
leading batch axes; the last axis (or last two, for matrices) is the object itself."""

from needlecli.numerics.angles import wrap_angle, angle_diff
from needlecli.numerics.integrate import rk4_step, complex_step_jacobian, finite_difference_jacobian
from needlecli.numerics.rotations import (
    hat,
    vee,
    rot_x,
    rot_y,
    rot_z,
    euler_xyz_to_matrix,
    matrix_to_euler_xyz,
    so3_exp,
    so3_log,
    rotation_angle,
    project_to_so3,
)

__all__ = [
    "wrap_angle",
    "angle_diff",
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
]
