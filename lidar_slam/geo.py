"""The Earth: a local ENU frame (x east, y north, z up) at a datum on WGS84, through PROJ
(pyproj, the `geo` extra; imported only when used). Exact topocentric conversions, no flat-earth
approximation. Heights are ellipsoidal (above the WGS84 ellipsoid, not above the geoid).

UTM: the zone is the one holding the datum (WGS 84 / UTM zone N: EPSG 326NN north of the equator,
327NN south, the standard 6-degree zones without the Norway / Svalbard exceptions).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from lidar_slam.errors import RunFailed


def _pyproj():
    try:
        import pyproj  # the geo extra
    except ImportError as exc:
        raise RunFailed("GNSS needs pyproj: pip install 'lidar-slam[geo]'") from exc
    return pyproj


def require_pyproj() -> None:
    """RunFailed, in one line, when the geo extra is not installed."""
    _pyproj()


@functools.lru_cache(maxsize=8)
def _transformer(lat0: float, lon0: float, h0: float):
    Transformer = _pyproj().Transformer
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

    @property
    def utm_epsg(self) -> int:
        """EPSG code of the UTM zone holding the datum (see utm_epsg)."""
        return utm_epsg(self.lat_deg, self.lon_deg)

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


@functools.lru_cache(maxsize=64)
def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS 84 / UTM zone holding a point (326NN north, 327NN south), from
    PROJ's database; on a zone border the zone east of it (lon in [west, east))."""
    pyproj = _pyproj()
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    if not (abs(lat_deg) <= 84.0 and np.isfinite(lon_deg)):
        raise RunFailed(f"no UTM zone at lat {lat_deg:g} deg, lon {lon_deg:g} deg (UTM ends at "
                        f"84 deg N / 80 deg S)")
    found = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(
        lon_deg, lat_deg, lon_deg, lat_deg))
    found = [c for c in found if c.auth_name == "EPSG" and not c.deprecated
             and int(c.code) // 100 in (326, 327)]
    inside = [c for c in found if c.area_of_use.west <= lon_deg < c.area_of_use.east
              and c.area_of_use.south <= lat_deg < c.area_of_use.north]
    if not (inside or found):
        raise RunFailed(f"pyproj {pyproj.__version__} knows no UTM zone at lat {lat_deg:g} deg, "
                        f"lon {lon_deg:g} deg")
    return int((inside or found)[0].code)


@functools.lru_cache(maxsize=8)
def _utm_transformer(epsg: int):
    """WGS84 (lon, lat, ellipsoidal height) -> (easting, northing, the same height)."""
    pyproj = _pyproj()
    return pyproj.Transformer.from_crs(pyproj.CRS.from_epsg(4979), pyproj.CRS.from_epsg(epsg),
                                       always_xy=True)


def wgs84_to_utm(lat_lon_h: np.ndarray, epsg: int) -> np.ndarray:
    """(N, 3) lat deg, lon deg, ellipsoidal height m -> (N, 3) UTM easting, northing (m) in the
    zone of EPSG code epsg, and the ellipsoidal height (m) unchanged."""
    llh = np.atleast_2d(np.asarray(lat_lon_h, dtype=float))
    e, n, h = _utm_transformer(int(epsg)).transform(llh[:, 1], llh[:, 0], llh[:, 2])
    return np.c_[e, n, h]


def utm_to_wgs84(enh: np.ndarray, epsg: int) -> np.ndarray:
    """The inverse of wgs84_to_utm: (N, 3) easting, northing, height m -> lat, lon deg, h m."""
    enh = np.atleast_2d(np.asarray(enh, dtype=float))
    lon, lat, h = _utm_transformer(int(epsg)).transform(enh[:, 0], enh[:, 1], enh[:, 2],
                                                        direction="INVERSE")
    return np.c_[lat, lon, h]


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

    def map_to_utm(self, points_map: np.ndarray) -> np.ndarray:
        """(N, 3) map-frame points (m) -> (N, 3) UTM easting, northing (m, zone utm_epsg) and
        ellipsoidal height (m)."""
        return wgs84_to_utm(self.map_to_wgs84(points_map), self.utm_epsg)

    @property
    def utm_epsg(self) -> int:
        """EPSG code of the UTM zone of the ENU datum (32632: WGS 84 / UTM zone 32N)."""
        return self.enu.utm_epsg

    def utm_crs(self):
        """The pyproj CRS of utm_epsg (WGS 84 / UTM zone N)."""
        return _pyproj().CRS.from_epsg(self.utm_epsg)

    @property
    def origin_wgs84(self) -> tuple[float, float, float]:
        """The map frame's origin: lat deg, lon deg, ellipsoidal height m."""
        lat, lon, h = self.map_to_wgs84(np.zeros(3))[0]
        return float(lat), float(lon), float(h)

    @property
    def heading_deg(self) -> float:
        """Compass heading of the map frame's x axis at its origin: degrees clockwise from true
        (geodetic) north, in [0, 360), of the axis projected on the horizontal plane there."""
        ends = self.map_to_wgs84(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
        east, north, _ = LocalEnu(*ends[0]).from_wgs84(ends[1])[0]
        return float(math.degrees(math.atan2(east, north)) % 360.0)

    def to_dict(self) -> dict:
        """The summary.json `geo` section (also what open_map reads back, see from_dict)."""
        lat, lon, h = self.origin_wgs84
        return {"origin_lat_deg": lat, "origin_lon_deg": lon, "origin_alt_m": h,
                "heading_deg": self.heading_deg,
                "enu_datum": {"lat_deg": self.enu.lat_deg, "lon_deg": self.enu.lon_deg,
                              "alt_m": self.enu.alt_m},
                "T_enu_map": np.asarray(self.T_enu_map, dtype=float).tolist(),
                "utm_epsg": self.utm_epsg}

    @classmethod
    def from_dict(cls, d: dict) -> GeoReference:
        """The GeoReference of a to_dict section; ValueError (saying what) when it is not one."""
        try:
            datum = d["enu_datum"]
            enu = LocalEnu(float(datum["lat_deg"]), float(datum["lon_deg"]),
                           float(datum["alt_m"]))
            T = np.asarray(d["T_enu_map"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"geo: not a geo reference ({type(exc).__name__}: {exc})") from None
        if not (np.isfinite(enu.datum).all() and abs(enu.lat_deg) <= 90.0):
            raise ValueError(f"geo: enu_datum {enu.datum} is not a WGS84 point")
        if T.shape != (4, 4) or not np.isfinite(T).all() \
                or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) \
                or not np.allclose(T[3], [0, 0, 0, 1]) or np.linalg.det(T[:3, :3]) < 0:
            raise ValueError("geo: T_enu_map is not a rigid 4x4 transform")
        return cls(enu, T)
