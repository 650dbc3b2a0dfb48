"""The range terms' choices kept for a solve again on the same inputs (a re-solve from the measurement cache).

Under ``--range-model auto`` the choice (``range_terms_choice.choose_range_model``: each block of terms fitted and
tested, a dozen GTSAM solves) is two fifths of a cached re-solve's time, and it is a pure function of the
refinement's inputs. A refinement given a memo (a dict) keys it by the digest of its inputs' content
(:func:`inputs_digest`: the frames, board, camera, start and options, every array's bytes) and keeps there each
choice's :func:`decision`; on inputs of the same digest the decisions are replayed, only the chosen model
solved (``choose_range_model``'s ``decided``), so the result is the one the tests gave. The memo's file is the
pipeline's (beside the measurements in the cache, whose key holds the code's version).
"""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import PurePath

import numpy as np

from .range_model import RANGE_MODELS, RangeModelFit

# What a decision holds: the record's fields the choice itself set (the chosen model's terms and values come
# from solving it again).
DECIDED = ("requested", "chosen", "reason", "tests", "left_out", "weak_offset", "range_accuracy_m")


class Undigestible(TypeError):
    """An input of a type the digest does not read: the refinement then chooses without the memo."""


def inputs_digest(*parts) -> str:
    """SHA-256 over the content of ``parts``: dataclasses field by field, arrays by dtype, shape and bytes, numbers
    by their exact value (of any type), containers in order (dicts by sorted keys). :class:`Undigestible` for any other
    type, rather than a digest of something the content might not fix."""
    h = hashlib.sha256()
    for part in parts:
        _feed(h, part)
    return h.hexdigest()


def _feed(h, x) -> None:
    # Numbers by value whatever their type (a measured plane's distance is numpy's float, the cached one Python's).
    if x is None:
        h.update(b"None;")
    elif isinstance(x, (bool, np.bool_)):
        h.update(f"bool:{bool(x)};".encode())
    elif isinstance(x, (int, np.integer)):
        h.update(f"int:{int(x)};".encode())
    elif isinstance(x, (float, np.floating)):
        h.update(f"float:{float(x).hex()};".encode())
    elif isinstance(x, (str, PurePath)):
        h.update(f"{type(x).__name__}:{x!s};".encode())
    elif isinstance(x, np.ndarray):
        if x.dtype == object:
            raise Undigestible("an array of objects")
        h.update(f"array:{x.dtype.str}:{x.shape};".encode())
        h.update(np.ascontiguousarray(x).tobytes())
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        h.update(f"{type(x).__qualname__}{{".encode())
        for f in dataclasses.fields(x):
            h.update(f.name.encode())
            _feed(h, getattr(x, f.name))
        h.update(b"}")
    elif isinstance(x, (list, tuple)):
        h.update(f"seq:{len(x)}[".encode())
        for v in x:
            _feed(h, v)
        h.update(b"]")
    elif isinstance(x, (dict, frozenset, set)):
        items = sorted(x.items() if isinstance(x, dict) else ((v, None) for v in x), key=lambda kv: repr(kv[0]))
        h.update(f"map:{len(items)}{{".encode())
        for k, v in items:
            _feed(h, k)
            _feed(h, v)
        h.update(b"}")
    else:
        raise Undigestible(f"a {type(x).__name__}")


def decision(fit: RangeModelFit) -> dict:
    """What a choice decided, as JSON holds it (floats exactly: ``json`` writes their ``repr``)."""
    d = {k: getattr(fit, k) for k in DECIDED}
    return {**d, "tests": [dict(t) for t in fit.tests], "left_out": list(fit.left_out)}


def decided_fields(d: dict) -> dict:
    """A :func:`decision` read back as ``RangeModelFit``'s fields."""
    return {**{k: d[k] for k in DECIDED}, "tests": tuple(d["tests"]), "left_out": tuple(d["left_out"])}


def recallable(kept: dict) -> dict:
    """The entries of a memo read back from a file (``io.measurement_store.load_choices``) that hold one or two
    decisions of :func:`decision`'s form, with what later steps read of them (the tests' models and p-values, a
    weak offset's shift); a damaged or foreign entry is left out, to be chosen again."""
    return {k: v for k, v in kept.items() if isinstance(v, list) and 1 <= len(v) <= 2 and all(map(_decision, v))}


def _decision(d) -> bool:
    def number(x) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    def test(t) -> bool:
        return isinstance(t, dict) and number(t.get("p_value")) and isinstance(t.get("included"), bool) and \
            isinstance(t.get("model"), str) and isinstance(t.get("against"), str)

    def weak(w) -> bool:
        return w is None or isinstance(w, dict) and number(w.get("p_value")) and number(w.get("offset_mm")) and \
            isinstance(w.get("with_ring_ends"), bool) and isinstance(w.get("difference_tangent"), list) and \
            len(w["difference_tangent"]) == 6 and all(number(x) for x in w["difference_tangent"])

    return (isinstance(d, dict) and d.get("chosen") in RANGE_MODELS and d["chosen"] != "auto"
            and d.get("requested") == "auto" and isinstance(d.get("reason"), str) and isinstance(d.get("tests"), list)
            and all(map(test, d["tests"])) and isinstance(d.get("left_out"), list)
            and all(isinstance(m, str) for m in d["left_out"]) and weak(d.get("weak_offset"))
            and number(d.get("range_accuracy_m")))
