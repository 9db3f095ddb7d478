"""filterpy's KalmanFilter class, without the rest of filterpy.

`from filterpy.kalman import KalmanFilter` runs filterpy's package initialisers, which import
every filter it has (unscented, ensemble, IMM...) and with them scipy.stats and scipy.linalg:
about 1 s of start-up on a desktop core (3-5 s on a Pi) and 70 MB of resident memory, for a
class that needs neither. The class itself (`filterpy/kalman/kalman_filter.py`) imports only
numpy, the standard library, `filterpy.stats.logpdf` (used by its log-likelihood property,
which netpose never reads) and two small helpers from `filterpy/common/helpers.py`.

So the file is loaded by itself, from the installed filterpy, unmodified: its two filterpy
imports are answered by the helpers module (loaded the same way) and a numpy logpdf, through an
`__import__` private to that one module. Nothing is registered in `sys.modules`, so an
`import filterpy` elsewhere still gets the real package. `tests/test_tracking.py` checks the
class against the one filterpy's package exports.
"""

from __future__ import annotations

import builtins
import importlib.util
import math
import types
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt


def logpdf(
    x: npt.ArrayLike, mean: npt.ArrayLike | None = None, cov: npt.ArrayLike = 1,
    allow_singular: bool = True,
) -> float:
    """Log of the multivariate normal density (filterpy.stats.logpdf's contract; a singular
    covariance uses its pseudo-inverse and pseudo-determinant, as scipy does)."""
    xv = np.atleast_1d(np.asarray(x, dtype=float)).ravel()
    mv = np.zeros_like(xv) if mean is None else np.atleast_1d(np.asarray(mean, float)).ravel()
    cv = np.atleast_2d(np.asarray(cov, dtype=float))
    if cv.shape == (1, 1) and xv.size > 1:
        cv = np.eye(xv.size) * float(cv[0, 0])
    eigenvalues = np.linalg.eigvalsh(cv)
    if allow_singular:
        kept = eigenvalues > 1e-12 * max(float(np.abs(eigenvalues).max()), 1e-300)
        inverse = np.linalg.pinv(cv)
        logdet, rank = float(np.sum(np.log(eigenvalues[kept]))), int(kept.sum())
    else:
        inverse = np.linalg.inv(cv)
        logdet, rank = float(np.sum(np.log(eigenvalues))), xv.size
    d = xv - mv
    return float(-0.5 * (d @ inverse @ d + logdet + rank * math.log(2.0 * math.pi)))


def _filterpy_file(*parts: str) -> Path:
    spec = importlib.util.find_spec("filterpy")  # locates the package, does not import it
    if spec is None or spec.origin is None:
        raise ImportError("filterpy is not installed")
    return Path(spec.origin).parent.joinpath(*parts)


def _load(path: Path, name: str, substitutes: Mapping[str, types.ModuleType]) -> types.ModuleType:
    """Execute one source file as a module whose imports of `substitutes` are answered by them."""
    module = types.ModuleType(name)
    module.__file__ = str(path)

    def private_import(
        target: str, globals: Mapping[str, Any] | None = None,
        locals: Mapping[str, Any] | None = None, fromlist: Sequence[str] = (), level: int = 0,
    ) -> types.ModuleType:
        if level == 0 and target in substitutes:
            return substitutes[target]
        return builtins.__import__(target, globals, locals, fromlist, level)

    module.__dict__["__builtins__"] = {**vars(builtins), "__import__": private_import}
    code = compile(path.read_text(encoding="utf-8"), str(path), "exec")
    exec(code, module.__dict__)  # filterpy's own source, unmodified
    return module


def load_kalman_filter() -> type:
    """filterpy.kalman.KalmanFilter, loaded without filterpy's package initialisers."""
    stats = types.ModuleType("filterpy.stats")
    stats.logpdf = logpdf  # type: ignore[attr-defined]
    helpers = _load(_filterpy_file("common", "helpers.py"), "filterpy.common.helpers", {})
    common = types.ModuleType("filterpy.common")
    common.pretty_str = helpers.pretty_str  # type: ignore[attr-defined]
    common.reshape_z = helpers.reshape_z  # type: ignore[attr-defined]
    module = _load(_filterpy_file("kalman", "kalman_filter.py"), "filterpy.kalman.kalman_filter",
                   {"filterpy.stats": stats, "filterpy.common": common})
    kalman_filter: type = module.KalmanFilter
    return kalman_filter
