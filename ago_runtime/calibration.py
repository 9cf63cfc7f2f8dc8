"""Old import path of `ago_runtime.formats.calibration`, kept for users: the same module object."""

import sys

from ago_runtime.formats import calibration as _moved

sys.modules[__name__] = _moved
