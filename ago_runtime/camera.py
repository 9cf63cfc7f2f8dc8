"""Old import path of `ago_runtime.geometry.camera`, kept for users: the same module object."""

import sys

from ago_runtime.geometry import camera as _moved

sys.modules[__name__] = _moved
