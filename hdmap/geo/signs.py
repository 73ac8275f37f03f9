"""Traffic-sign classes: wire codes, names and standard physical sizes.

The panel height (metres) turns a bounding-box height in pixels into a range
(:mod:`vehicle.geoloc`). Sizes are typical urban sizes of the Vienna-convention
signs used in Finland ("normal" size class, 640 mm discs and squares, 900 mm
triangles whose height is 0.78 m); a deployment overrides them per class from
the vehicle config file.

>>> CATALOG.by_name("speed_limit_30").height_m
0.64
>>> CATALOG.code("stop")
1
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SignClass:
    code: int
    name: str
    height_m: float
    size_rel_sigma: float = 0.10
    """Relative standard deviation of the real panel size around ``height_m``."""


_DEFAULT_CLASSES: tuple[SignClass, ...] = (
    SignClass(1, "stop", 0.75),
    SignClass(2, "give_way", 0.78),
    SignClass(3, "no_entry", 0.64),
    SignClass(4, "speed_limit_30", 0.64),
    SignClass(5, "speed_limit_40", 0.64),
    SignClass(6, "speed_limit_50", 0.64),
    SignClass(7, "no_parking", 0.64),
    SignClass(8, "no_stopping", 0.64),
    SignClass(9, "pedestrian_crossing", 0.64),
    SignClass(10, "priority_road", 0.64),
    SignClass(11, "one_way", 0.64),
    SignClass(12, "parking", 0.64),
    SignClass(13, "roundabout", 0.64),
    SignClass(14, "keep_right", 0.64),
    SignClass(15, "children", 0.78),
    SignClass(16, "road_works", 0.78),
    SignClass(17, "bus_stop", 0.64),
    SignClass(18, "no_turn", 0.64),
    SignClass(19, "cycle_path", 0.64),
    SignClass(20, "dead_end", 0.64),
)


class SignCatalog:
    """Immutable lookup of sign classes by code and by name."""

    def __init__(self, classes: Iterable[SignClass]):
        self._by_code = {c.code: c for c in classes}
        self._by_name = {c.name: c for c in self._by_code.values()}
        if len(self._by_name) != len(self._by_code):
            raise ValueError("sign class names must be unique")
        max_code = max(self._by_code, default=0)
        self._height = np.zeros(max_code + 1)
        self._rel = np.zeros(max_code + 1)
        for c in self._by_code.values():
            self._height[c.code] = c.height_m
            self._rel[c.code] = c.size_rel_sigma

    def __len__(self) -> int:
        return len(self._by_code)

    def __iter__(self):
        return iter(sorted(self._by_code.values(), key=lambda c: c.code))

    def __contains__(self, code: object) -> bool:
        return code in self._by_code

    def by_code(self, code: int) -> SignClass:
        return self._by_code[int(code)]

    def by_name(self, name: str) -> SignClass:
        return self._by_name[name]

    def code(self, name: str) -> int:
        return self._by_name[name].code

    @property
    def codes(self) -> NDArray[np.int64]:
        return np.array(sorted(self._by_code), dtype=np.int64)

    def known(self, codes: NDArray) -> NDArray[np.bool_]:
        """Vectorised membership test."""
        c = np.asarray(codes, dtype=np.int64)
        ok = (c >= 0) & (c < self._height.size)
        out = np.zeros(c.shape, bool)
        out[ok] = self._height[c[ok]] > 0
        return out

    def heights(self, codes: NDArray) -> NDArray[np.float64]:
        """Panel heights (m) per code; 0 for unknown codes."""
        c = np.asarray(codes, dtype=np.int64)
        out = np.zeros(c.shape)
        ok = self.known(c)
        out[ok] = self._height[c[ok]]
        return out

    def rel_sigmas(self, codes: NDArray) -> NDArray[np.float64]:
        c = np.asarray(codes, dtype=np.int64)
        out = np.zeros(c.shape)
        ok = self.known(c)
        out[ok] = self._rel[c[ok]]
        return out

    def with_sizes(self, heights_m: Mapping[str, float]) -> SignCatalog:
        """A copy with some panel heights overridden (by class name)."""
        unknown = set(heights_m) - set(self._by_name)
        if unknown:
            raise ValueError(f"unknown sign classes in size overrides: {sorted(unknown)}")
        return SignCatalog(
            replace(c, height_m=float(heights_m.get(c.name, c.height_m)))
            for c in self._by_code.values()
        )


CATALOG = SignCatalog(_DEFAULT_CLASSES)
"""The default catalogue (immutable)."""
