"""Old import path of `ago_runtime.formats.frame`, kept for users: the same module object."""

import sys

from ago_runtime.formats import frame as _moved

sys.modules[__name__] = _moved
