"""Scene geometry for the prepasses: diffuse patches built from a loaded ``mi.Scene``."""
from .patches import Patches, build_patches

__all__ = ["Patches", "build_patches"]
