"""Rate-distortion helpers: the Pareto front of (bits per point, distortion) pairs and the distortion it reaches
at a given rate, interpolated linearly in log(bpp). Pool several codecs' points to get "the best classical codec
at the same bpp"."""

import numpy as np

from mapsqueeze.errors import BaselineError


def _checked_pairs(bpp, distortion) -> tuple[np.ndarray, np.ndarray]:
    rates, errors = np.asarray(bpp, dtype=np.float64), np.asarray(distortion, dtype=np.float64)
    if rates.ndim != 1 or rates.shape != errors.shape or len(rates) == 0:
        raise BaselineError(f"rate-distortion: need two equal-length 1-D arrays, got {rates.shape} and {errors.shape}")
    if not (np.isfinite(rates).all() and np.isfinite(errors).all() and (rates > 0).all()):
        raise BaselineError("rate-distortion: bpp must be positive and finite, distortion finite")
    return rates, errors


def pareto_front(bpp, distortion) -> np.ndarray:
    """Indices of the non-dominated (bpp, distortion) points, by increasing bpp (so decreasing distortion).

    A point is dominated when another has lower-or-equal bpp and strictly lower distortion, or equal distortion
    at strictly lower bpp; of identical points the first is kept.
    """
    rates, errors = _checked_pairs(bpp, distortion)
    order = np.lexsort((errors, rates))  # by bpp, ties by distortion
    best_so_far = np.minimum.accumulate(errors[order])
    improves = np.ones(len(order), dtype=bool)
    improves[1:] = errors[order][1:] < best_so_far[:-1]
    return order[improves]


def distortion_at(bpp, distortion, query_bpp) -> np.ndarray:
    """Distortion of the Pareto front of (bpp, distortion) at `query_bpp` (scalar or array), linear in log(bpp).

    Between the front's last point and the highest measured bpp (dominated settings) the front holds its lowest
    distortion; NaN below the lowest and above the highest measured bpp (no extrapolation).
    """
    rates, errors = _checked_pairs(bpp, distortion)
    front = pareto_front(rates, errors)
    query = np.asarray(query_bpp, dtype=np.float64)
    log_query = np.log(np.where(query > 0, query, np.nan))
    log_front = np.log(rates[front])
    result = np.interp(log_query, log_front, errors[front])
    return np.where((log_query >= log_front[0]) & (log_query <= np.log(rates.max())), result, np.nan)
