"""Suite-wide settings.

The disk cache of exported ONNX graphs (:mod:`seqshape.model.graph_cache`) is off for the
suite: tests build engines from graphs they have just exported, never from a file another
test (or an earlier run of the suite, or the user's own sessions) left behind. The cache's
own tests turn it on in a temporary folder.
"""

import os

os.environ["SEQSHAPE_CACHE_DIR"] = "none"
