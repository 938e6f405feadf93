"""Local building metres <-> WGS-84 on a local tangent plane (accurate to centimetres over a building).

A local point (x, y) is rotated counter-clockwise by ``rotation_rad`` into east/north metres, which are
scaled by the WGS-84 meridional (M) and prime-vertical (N) radii of curvature at the origin's latitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

WGS84_A = 6_378_137.0
WGS84_E2 = 6.694_379_990_14e-3


@dataclass(frozen=True)
class GeoFrame:
    origin_lat_deg: float
    origin_lon_deg: float
    rotation_rad: float = 0.0

    def _radii(self) -> tuple[float, float]:
        s = math.sin(math.radians(self.origin_lat_deg))
        w = math.sqrt(1.0 - WGS84_E2 * s * s)
        meridional = WGS84_A * (1.0 - WGS84_E2) / w**3
        prime_vertical = WGS84_A / w
        return meridional, prime_vertical * math.cos(math.radians(self.origin_lat_deg))

    def to_wgs84(self, x: float, y: float) -> tuple[float, float]:
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        east, north = c * x - s * y, s * x + c * y
        m, n_cos = self._radii()
        return self.origin_lat_deg + math.degrees(north / m), self.origin_lon_deg + math.degrees(east / n_cos)

    def to_local(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        m, n_cos = self._radii()
        north = math.radians(lat_deg - self.origin_lat_deg) * m
        east = math.radians(lon_deg - self.origin_lon_deg) * n_cos
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return c * east + s * north, -s * east + c * north
