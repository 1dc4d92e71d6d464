"""ViSNeRF: visualization-aware neural radiance fields for post hoc exploration."""

import os

# torch's OpenMP workers sleep as soon as a parallel op ends, instead of spinning on the core that
# the compiled loops' helper thread needs (``compiled.run_parts``). libgomp reads this once, when
# torch loads it, so it takes effect where this package is imported before torch (the ``visnerf``
# command, the server, the benchmarks); a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
