"""Old import path of `ago_runtime.geometry.grid`, kept for users: the same module object."""

import sys

from ago_runtime.geometry import grid as _moved

sys.modules[__name__] = _moved
