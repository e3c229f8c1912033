"""Robot arms from URDF kinematics: energy regressor terms, base parameters, write-back."""
