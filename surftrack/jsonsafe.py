"""JSON without NaN or infinities, for files that strict readers (Foxglove, ``json.loads`` elsewhere) accept.

Used by any stage that writes JSON (the evaluation's results, the MCAP log's free-form fields); it
imports nothing from surftrack.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def json_safe(x: Any) -> Any:
    """``x`` ready for ``json.dumps(..., allow_nan=False)``: non-finite floats become None (JSON has no
    NaN or infinity), recursively through mappings (keys made str), lists and tuples (made lists);
    numpy scalars become Python numbers. Other values are returned as they are."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Mapping):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.generic):
        return json_safe(x.item())
    return x
