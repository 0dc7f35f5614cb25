"""kinefuse: IMU (+ optional camera) human joint position capture.

Public API re-exports only; see the subpackages for the implementations.
"""

from kinefuse.models import LinearGaussianModel, constant_velocity

__version__ = "0.1.0"

__all__ = ["LinearGaussianModel", "__version__", "constant_velocity"]
