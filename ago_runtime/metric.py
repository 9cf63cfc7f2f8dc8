"""Old import path of `ago_runtime.scoring.metric`, kept for users: the same module object."""

import sys

from ago_runtime.scoring import metric as _moved

sys.modules[__name__] = _moved
