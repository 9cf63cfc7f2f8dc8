"""Old import path of `ago_runtime.predict.predictor`, kept for users: the same module object."""

import sys

from ago_runtime.predict import predictor as _moved

sys.modules[__name__] = _moved
