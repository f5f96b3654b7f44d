"""Comparisons shared by the tests: tolerances across code paths, exactness only as a contract.

Two computations of the same maths (a grown network with zero-started columns and its init, a
traced graph and the eager forward, batch 1 and batch 8) may differ in the last bits on another
CPU: oneDNN and MKL choose kernels, blockings and summation orders by instruction set. They are
compared with ``assert_outputs_close``. A tensor that was only copied, never recomputed (a frozen
parameter, a weights file read back) must be identical: ``changed_keys`` compares those exactly.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import torch

# Network outputs are metres, radians, logits and unit-box coordinates of order 1: a float32
# reordering moves them by ~1e-7; a real change (a trained step, another branch) by far more.
ATOL = 1e-5
RTOL = 1e-5


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().float().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def assert_outputs_close(got: Mapping[str, Any], want: Mapping[str, Any], keys: Iterable[str],
                         atol: float = ATOL, rtol: float = RTOL) -> None:
    """Each named output of ``got`` equals ``want``'s within float32 reordering noise."""
    for k in keys:
        np.testing.assert_allclose(_np(got[k]), _np(want[k]), atol=atol, rtol=rtol, err_msg=k)


def outputs_differ(a: Any, b: Any, atol: float = 1e-4) -> bool:
    """Whether two outputs differ by clearly more than reordering noise."""
    return not np.allclose(_np(a), _np(b), atol=atol, rtol=0.0)


def changed_keys(sa: Mapping[str, torch.Tensor], sb: Mapping[str, torch.Tensor],
                 ignore: Iterable[str] = ()) -> set[str]:
    """State-dict entries that differ at all. Frozen parameters are copied, not recomputed, so
    exactness is the contract here: any difference means the module was trained or re-made."""
    skip = set(ignore)
    return {k for k in sa if k not in skip and not _identical(sa[k], sb.get(k))}


def _identical(a: torch.Tensor, b: torch.Tensor | None) -> bool:
    return b is not None and a.shape == b.shape and a.dtype == b.dtype and bool((a == b).all())
