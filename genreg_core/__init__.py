"""genreg_core: GenReg registration in pure Python (torch + numpy), no ROS.

Conventions: points are rows of (N, 3) arrays; transforms are 4x4 matrices acting on column
vectors, x' = R x + t; `RegistrationResult.transformation` maps source points into the target frame.
"""
