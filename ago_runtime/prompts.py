"""Old import path of `ago_runtime.vocab.prompts`, kept for users: the same module object."""

import sys

from ago_runtime.vocab import prompts as _moved

sys.modules[__name__] = _moved
