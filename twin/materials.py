"""Material parameters of the simulated skin module, with their sources.

The numbers come from the sensor design (``design.skin``, ``design.gel``, ``design.pins``); this
module documents where they come from and adds what the design does not state.

Sources
-------
* Skin and pins, Stratasys Agilus30 (Shore A 30, paper Sec. II-A): Young's modulus from the Shore A
  hardness by Gent's relation, E = 0.0981 (56 + 7.62336 S) / (0.137505 (254 - 2.54 S)) MPa
  (A. N. Gent, Trans. Inst. Rubber Ind. 34, 1958), S = 30 -> E = 1.14 MPa. Poisson ratio 0.45: a
  nearly incompressible photopolymer elastomer, slightly below 0.5 so linear tetrahedra do not lock.
* Gel, Techsil RTV27905 optically clear silicone gel (cone penetration 3-7 mm): the vendor gives
  penetration only. Silicone gels of this penetration class have moduli of order 10-50 kPa; the
  designs use E = 20 kPa. Poisson ratio 0.49 (gels are nearly incompressible).
* Rigid parts (mount, acrylic window, indenters) are not simulated as materials: the mount and
  window are fixed boundary conditions, indenters are kinematic (position-controlled) bodies.

Numerical choices (not material data)
-------------------------------------
* Mass: the physical gel (density ~1000 kg/m^3, ~13 g) is replaced by a per-vertex mass chosen
  for the solver, ``m_i = MASS_SCALE * dt^2 * K_ii`` (K_ii: the vertex's diagonal stiffness). Under
  displacement control the quasi-static equilibrium does not depend on mass (nor on damping), so
  the scaling only changes how fast the solver reaches it; it keeps the effective metric
  ``M + dt^2 K`` of MuJoCo's discrete integrator well conditioned. Gravity is off (the gel's
  weight, ~0.1 N, is negligible against contact forces and absent from the paper's analysis).
* Damping: a tiny Rayleigh damping (``RAYLEIGH_DAMPING_S``) only; implicit Euler of the discrete
  integrator removes the remaining oscillation.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.design import SensorDesign

__all__ = ["Material", "skin_material", "gel_material", "shore_a_to_youngs_mpa", "MASS_SCALE", "RAYLEIGH_DAMPING_S"]

MASS_SCALE = 0.05          # m_i / (dt^2 K_ii). Contact stiffness scales with it: at 0.035 and 0.02 skin vertices
                           # slipped through a sine's steep flanks (ω = π/5: 1.0-1.7 mm inside; 0.05: 0.005 mm),
                           # although 0.02 settled the σ² = 10 press in half the steps; at 0.01 MuJoCo's M + h²K
                           # solve ran out of iterations (mjWARN_INERTIA)
RAYLEIGH_DAMPING_S = 1e-4  # s; << timestep, present so MuJoCo registers the flex's passive forces


@dataclass(frozen=True)
class Material:
    """A linear-elastic material: name, Young's modulus (MPa), Poisson ratio, source note."""

    name: str
    youngs_modulus_mpa: float
    poisson_ratio: float
    source: str


def shore_a_to_youngs_mpa(shore_a: float) -> float:
    """Gent's relation between Shore A hardness and Young's modulus (MPa), valid ~20 < S < 80."""
    s = float(shore_a)
    return 0.0981 * (56.0 + 7.62336 * s) / (0.137505 * (254.0 - 2.54 * s))


def skin_material(design: SensorDesign) -> Material:
    """The skin layer's material (from ``design.skin``)."""
    s = design.skin
    return Material(s.material, s.youngs_modulus_mpa, s.poisson_ratio, s.source)


def gel_material(design: SensorDesign) -> Material:
    """The gel's material (from ``design.gel``)."""
    g = design.gel
    return Material(g.material, g.youngs_modulus_mpa, g.poisson_ratio, g.source)
