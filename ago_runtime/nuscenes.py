"""Old import path of `ago_runtime.formats.nuscenes`, kept for users: the same module object."""

import sys

from ago_runtime.formats import nuscenes as _moved

sys.modules[__name__] = _moved
