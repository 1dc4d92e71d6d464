"""ViSNeRF: visualization-aware neural radiance fields for post hoc exploration."""

__version__ = "0.1.0"
