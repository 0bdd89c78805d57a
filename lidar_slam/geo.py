"""The Earth: a local ENU frame (x east, y north, z up) at a datum on WGS84, through PROJ
(pyproj, the `geo` extra; imported only when used). Exact topocentric conversions, no flat-earth
approximation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_slam.errors import RunFailed


def _transformer(lat0: float, lon0: float, h0: float):
    try:
        from pyproj import Transformer  # the geo extra
    except ImportError as exc:
        raise RunFailed("GNSS needs pyproj: pip install 'lidar-slam[geo]'") from exc
    # float(): the repr of a NumPy scalar is "np.float64(49.0)", which PROJ misreads silently
    lat0, lon0, h0 = float(lat0), float(lon0), float(h0)
    pipe = ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            "+step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}")
    return Transformer.from_pipeline(pipe)


@dataclass(frozen=True)
class LocalEnu:
    """The ENU frame whose origin is the datum (lat deg, lon deg, ellipsoidal height m)."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    @property
    def datum(self) -> tuple[float, float, float]:
        return (self.lat_deg, self.lon_deg, self.alt_m)

    def to_wgs84(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) ENU (m) -> (N, 3) lat deg, lon deg, ellipsoidal height m."""
        enu = np.atleast_2d(np.asarray(enu_m, dtype=float))
        lon, lat, h = _transformer(*self.datum).transform(enu[:, 0], enu[:, 1], enu[:, 2],
                                                          direction="INVERSE")
        return np.c_[lat, lon, h]

    def from_wgs84(self, lat_lon_h: np.ndarray) -> np.ndarray:
        """(N, 3) lat deg, lon deg, ellipsoidal height m -> (N, 3) ENU (m)."""
        llh = np.atleast_2d(np.asarray(lat_lon_h, dtype=float))
        e, n, u = _transformer(*self.datum).transform(llh[:, 1], llh[:, 0], llh[:, 2])
        return np.c_[e, n, u]


def enu_to_wgs84(enu_m: np.ndarray, datum: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) local ENU (m) at datum (lat deg, lon deg, h m) -> (N, 3) lat deg, lon deg, h m."""
    return LocalEnu(*datum).to_wgs84(enu_m)


@dataclass(frozen=True)
class GeoReference:
    """Where a run's map frame lies on the Earth: T_enu_map (4x4) takes map-frame points (the
    frame of poses_kitti.txt, map.ply and the keyframes: the first scan's) into the ENU frame
    `enu` (whose datum is a WGS84 point near the run, e.g. its first GNSS fix). Set by the
    back-end when GNSS is used (lidar_slam.backend); outputs and export read it."""

    enu: LocalEnu
    T_enu_map: np.ndarray

    def map_to_enu(self, points_map: np.ndarray) -> np.ndarray:
        """(N, 3) map-frame points (m) -> (N, 3) ENU (m)."""
        p = np.atleast_2d(np.asarray(points_map, dtype=float))
        return p @ self.T_enu_map[:3, :3].T + self.T_enu_map[:3, 3]

    def map_to_wgs84(self, points_map: np.ndarray) -> np.ndarray:
        """(N, 3) map-frame points (m) -> (N, 3) lat deg, lon deg, ellipsoidal height m."""
        return self.enu.to_wgs84(self.map_to_enu(points_map))
