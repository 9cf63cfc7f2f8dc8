"""Old import path of `ago_runtime.formats.occ3d`, kept for users: the same module object."""

import sys

from ago_runtime.formats import occ3d as _moved

sys.modules[__name__] = _moved
