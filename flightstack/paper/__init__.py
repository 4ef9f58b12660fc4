"""The paper's mathematics (Saito et al., IFAC 2023): planar SE(3), projection, the visual motion
observer, the pursuit law, one GP expert, the fusion rules, the gain condition (Theorem 1), the target
laws and the error metrics. Pure functions and dataclasses on numpy arrays: no I/O, no threads, no clock.
"""
