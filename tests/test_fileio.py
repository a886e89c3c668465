"""`app.fileio.json_safe`: what strict JSON readers refuse never reaches them."""

from __future__ import annotations

import json
import math

import numpy as np

from app.fileio import json_safe


def test_json_safe_turns_what_strict_json_refuses_into_what_it_reads() -> None:
    value = {
        "nan": math.nan,
        "inf": -math.inf,
        "np_float": np.float32(0.5),
        "np_int": np.int64(7),
        "np_nan": np.float64("nan"),
        "pair": (1, np.bool_(True)),
        3: [{"deep": math.inf}],
    }
    safe = json_safe(value)
    assert safe == {
        "nan": None,
        "inf": None,
        "np_float": 0.5,
        "np_int": 7,
        "np_nan": None,
        "pair": [1, True],
        "3": [{"deep": None}],
    }
    assert type(safe["np_int"]) is int and type(safe["pair"][1]) is bool
    json.dumps(safe, allow_nan=False)  # raises on anything strict JSON refuses
