"""Old import path of `ago_runtime.vocab.text_encoder`, kept for users: the same module object."""

import sys

from ago_runtime.vocab import text_encoder as _moved

sys.modules[__name__] = _moved
