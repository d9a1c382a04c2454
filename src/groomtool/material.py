"""Material parameters of a hair fibre (SI units) and the stiffnesses derived from them."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Material:
    """A circular fibre of radius ``radius`` (m), Young's modulus ``young_modulus`` (Pa), shear
    modulus ``shear_modulus`` (Pa, default E/3, an isotropic Poisson ratio of 0.5), density (kg/m^3)
    and Coulomb friction coefficient ``friction``.

    Defaults are human hair: E = 3 GPa, radius 40 um, density 1300 kg/m^3, mu = 0.3.
    """

    young_modulus: float = 3.0e9
    radius: float = 40e-6
    density: float = 1300.0
    friction: float = 0.3
    shear_modulus: float | None = None
    gravity: float = 9.81

    def __post_init__(self) -> None:
        for name in ("young_modulus", "radius", "density"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"material parameter {name} must be positive and finite, got {v}")
        if not np.isfinite(self.friction) or self.friction < 0:
            raise ValueError(f"friction coefficient must be >= 0, got {self.friction}")
        if self.shear_modulus is not None and (not np.isfinite(self.shear_modulus) or self.shear_modulus <= 0):
            raise ValueError(f"shear modulus must be positive, got {self.shear_modulus}")

    @property
    def G(self) -> float:
        return self.shear_modulus if self.shear_modulus is not None else self.young_modulus / 3.0

    @property
    def area(self) -> float:
        """Cross-section S = pi a^2."""
        return np.pi * self.radius**2

    @property
    def second_moment(self) -> float:
        """I = pi a^4 / 4."""
        return np.pi * self.radius**4 / 4.0

    @property
    def bending_stiffness(self) -> float:
        """EI (N m^2)."""
        return self.young_modulus * self.second_moment

    @property
    def twist_stiffness(self) -> float:
        """GJ with J = 2 I (N m^2)."""
        return self.G * 2.0 * self.second_moment

    @property
    def linear_density(self) -> float:
        """rho S (kg/m)."""
        return self.density * self.area

    @property
    def stiffness_diag(self) -> np.ndarray:
        """(GJ, EI, EI): the per-unit-length stiffness of (twist, kappa1, kappa2)."""
        return np.array([self.twist_stiffness, self.bending_stiffness, self.bending_stiffness])

    def greenhill_length(self) -> float:
        """Length beyond which a vertical strand buckles under its own weight: 1.986 (EI / rhoS g)^(1/3)."""
        return 1.986 * (self.bending_stiffness / (self.linear_density * self.gravity)) ** (1.0 / 3.0)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["shear_modulus"] = self.G
        return d
