"""Fit of the density law A(r_s) = a * r_s^-b (paper Sec. IV-E, eq. 5 and 12)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import curve_fit

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.geometry.grid import grid_subsample

DEFAULT_GRIDS_M = (0.5, 0.75, 1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0)


@dataclass
class DensityFit:
    a: float
    b: float
    rmse: float  # root-mean-square residual of the fitted rate (embedding points per map point)
    grids_m: tuple[float, ...]
    mean_rates: tuple[float, ...]


def subsampling_rates(clouds: list[np.ndarray], grids_m=DEFAULT_GRIDS_M, map_size: float = 40.0) -> np.ndarray:
    """Mean over clouds of (points kept by grid subsampling at r) / (points), for each grid r (m)."""
    rates = np.zeros((len(clouds), len(grids_m)))
    for i, cloud in enumerate(clouds):
        local = ((cloud - cloud.min(axis=0)) / map_size).astype(np.float32)
        for j, r in enumerate(grids_m):
            rates[i, j] = len(grid_subsample(local, r / map_size)) / len(cloud)
    return rates.mean(axis=0)


def fit_density_law(clouds: list[np.ndarray], grids_m=DEFAULT_GRIDS_M, map_size: float = 40.0) -> DensityFit:
    """Least-squares fit of a, b to the mean subsampling rates (initialised by a log-log linear fit)."""
    if not clouds:
        raise MapsqueezeError("no clouds to fit the density law on")
    grids = np.asarray(grids_m, dtype=np.float64)
    rates = subsampling_rates(clouds, grids_m, map_size)
    slope, intercept = np.polyfit(np.log(grids), np.log(rates), 1)
    (a, b), _ = curve_fit(lambda r, a, b: a * r ** (-b), grids, rates, p0=(np.exp(intercept), -slope))
    rmse = float(np.sqrt(np.mean((a * grids ** (-b) - rates) ** 2)))
    return DensityFit(float(a), float(b), rmse, tuple(grids_m), tuple(float(v) for v in rates))
