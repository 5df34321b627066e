"""CNR's settings: the descriptor's filters, the regressor's widths and the cascade."""

from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class CNRConfig:
    """Descriptor, regressor and cascade settings (hashable: a static jit argument).

    Attributes:
      sigma_s: spatial σ of the bilateral filters, multiples of d̄.
      sigma_r: range σ on `|n_i − n_j|`; `None` means ∞ (no range weight).
      iterations: increasing filter iteration counts at which the normals are read.
      guide: `(i_s, i_r, i_it)` indices of the filtered normal that is the frame's z.
      feature: indices of the filtered normal that sets the frame's x and is the base
        the regressor corrects.
      hidden: hidden layer widths of each stage's MLP.
      n_stages: cascade length.
      vertex_iterations: vertex update passes per stage.
    """

    sigma_s: tuple[float, ...] = (1.0, 2.0)
    sigma_r: tuple[float | None, ...] = (0.1, 0.2, 0.35, 0.5, None)
    iterations: tuple[int, ...] = (1, 3, 8)
    guide: tuple[int, int, int] = (1, 4, 2)
    feature: tuple[int, int, int] = (0, 2, 1)
    hidden: tuple[int, ...] = (128, 128, 64)
    n_stages: int = 2
    vertex_iterations: int = 20

    def __post_init__(self):
        for name in ("sigma_s", "sigma_r", "iterations", "guide", "feature", "hidden"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if not self.sigma_s or any(not (math.isfinite(s) and s > 0) for s in self.sigma_s):
            raise ValueError(f"sigma_s must be finite numbers > 0, got {self.sigma_s}")
        if not self.sigma_r or any(
            r is not None and not (math.isfinite(r) and r > 0) for r in self.sigma_r
        ):
            raise ValueError(f"sigma_r must be numbers > 0 or None (∞), got {self.sigma_r}")
        its = self.iterations
        if not its or any(int(i) != i or i < 1 for i in its) or list(its) != sorted(set(its)):
            raise ValueError(f"iterations must be increasing integers >= 1, got {its}")
        sizes = (len(self.sigma_s), len(self.sigma_r), len(self.iterations))
        for name in ("guide", "feature"):
            idx = getattr(self, name)
            if len(idx) != 3 or any(not 0 <= i < n for i, n in zip(idx, sizes, strict=True)):
                raise ValueError(f"{name} must index (sigma_s, sigma_r, iterations), got {idx}")
        if any(int(w) != w or w < 1 for w in self.hidden):
            raise ValueError(f"hidden widths must be integers >= 1, got {self.hidden}")
        if int(self.n_stages) != self.n_stages or self.n_stages < 1:
            raise ValueError(f"n_stages must be an integer >= 1, got {self.n_stages}")
        if int(self.vertex_iterations) != self.vertex_iterations or self.vertex_iterations < 0:
            raise ValueError(f"vertex_iterations must be >= 0, got {self.vertex_iterations}")

    @property
    def n_filtered(self) -> int:
        return len(self.sigma_s) * len(self.sigma_r) * len(self.iterations)

    @property
    def descriptor_dim(self) -> int:
        """Numbers per face: 3 × (filtered normals + the unfiltered one)."""
        return 3 * (self.n_filtered + 1)

    def normal_index(self, which: tuple[int, int, int]) -> int:
        """Position of a filtered normal in the descriptor (0 is the unfiltered normal)."""
        i_s, i_r, i_it = which
        return 1 + (i_s * len(self.sigma_r) + i_r) * len(self.iterations) + i_it

    def to_dict(self) -> dict:
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> CNRConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown CNRConfig field(s): {', '.join(unknown)}")
        return cls(**d)


def _jsonable(x):
    return list(x) if isinstance(x, tuple) else x
