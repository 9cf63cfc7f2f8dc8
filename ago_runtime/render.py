"""Old import path of `ago_runtime.pictures.render`, kept for users: the same module object."""

import sys

from ago_runtime.pictures import render as _moved

sys.modules[__name__] = _moved
