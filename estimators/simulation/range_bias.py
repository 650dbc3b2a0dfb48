"""Systematic LiDAR range errors to inject into simulations: a global offset, per-ring offsets and an offset
on the board's black squares (measured range = true range + bias + noise). ``solvers.range_model`` estimates
the same terms."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RangeBias:
    offset_m: float = 0.0
    ring_offsets_m: tuple[float, ...] = ()  # by ring id; rings beyond the tuple get none
    dark_m: float = 0.0

    @staticmethod
    def drawn(rng: np.random.Generator, n_rings: int, offset_m: float, ring_sd_m: float, dark_m: float
              ) -> "RangeBias":
        """Per-ring offsets drawn from N(0, ring_sd_m^2) (deviations from the global offset)."""
        return RangeBias(offset_m, tuple(rng.normal(0.0, ring_sd_m, n_rings).tolist()) if ring_sd_m > 0 else (),
                         dark_m)

    def record(self) -> dict:
        """As a simulation records it (its ground truth's ``range_bias``; :meth:`from_record` reads it)."""
        return {"offset_m": self.offset_m, "ring_offsets_m": list(self.ring_offsets_m), "dark_m": self.dark_m}

    @staticmethod
    def from_record(record: dict) -> "RangeBias":
        """The bias a simulation recorded (ground_truth.json's ``range_bias`` of a LiDAR)."""
        return RangeBias(record["offset_m"], tuple(record["ring_offsets_m"]), record["dark_m"])

    def term(self, name: str) -> float:
        """The injected value (m) of a range term named as the range model names them: ``offset``, ``dark`` or
        ``ring <id>`` (a ring's deviation from the global offset)."""
        if name == "offset":
            return self.offset_m
        if name == "dark":
            return self.dark_m
        return self.ring_offsets_m[int(name.split()[1])]

    @property
    def is_zero(self) -> bool:
        return self.offset_m == 0 and not any(self.ring_offsets_m) and self.dark_m == 0

    def of(self, rings: np.ndarray, dark: np.ndarray) -> np.ndarray:
        """The bias (m) of returns with these ring ids and black-square flags."""
        b = np.full(len(rings), self.offset_m, dtype=float)
        if self.ring_offsets_m:
            table = np.asarray(self.ring_offsets_m, dtype=float)
            r = np.asarray(rings, dtype=int)
            ok = (r >= 0) & (r < len(table))
            b[ok] += table[r[ok]]
        return b + self.dark_m * np.asarray(dark, dtype=bool)
