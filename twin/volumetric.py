"""Average nodal volume ratio: the gel's bulk stiffness without volumetric locking.

Linear tetrahedra lock as ν → 0.5: each element must keep its own volume, and a mesh of linear
tetrahedra has about as many elements as degrees of freedom, so nearly incompressible deformation
is over-constrained (a sphere R = 10 mm pressed into a uniform ν = 0.49 gel: force 2.3× the bonded-
layer Hertz solution). The average nodal pressure tetrahedron (Bonet & Burton 1998, Commun. Numer.
Meth. Engng 14:437-449) constrains volume per *node* instead: about one constraint per three degrees
of freedom, which does not lock.

Split of the energy. Each material is given to MuJoCo's flex with its shear modulus μ kept and a
reduced Poisson ratio ``NU_DEV`` (little bulk stiffness: it cannot lock much), and the remaining bulk
modulus ``K = κ(E, ν) − κ(E', ν_dev)`` (κ = E/(3(1−2ν)), E' = 2μ(1+ν_dev)) is carried by

    U = Σ_n (K/2) V̄_n (J̄_n − 1)²,   J̄_n = Σ_t w_tn v_t / Σ_t w_tn V_t,   V̄_n = Σ_t w_tn V_t,

with v_t, V_t the current and rest volumes of the tetrahedra and w_tn = 1 / (number of active nodes of t)
for each active node n of t (every node, or only the free vertices: ``FREE_NODES_ONLY``), so the V̄_n
partition the body. A node of two materials has one term in each. A uniform dilation J gives
U = (K/2) V (J − 1)², pressure K (J − 1). Forces are the exact gradient, ∂v_t/∂x_i = (1/6) × the cross
product of the opposite edges.

In the twin (``MeshSpec(volumetric="nodal")``, set up in :mod:`twin.model`, applied in :mod:`twin.physics`)
the forces are evaluated at the start of every step and applied to the free vertices' slide DOFs (``qfrc_applied``, ~1.6 ms a step):
explicit, so the vertex masses are scaled by ``MASS_FACTOR`` for stability, the path is damped
(``DAMPING_PER_S``) and the constraint solve is converged tighter (``SOLVER_TOLERANCE``: at MuJoCo's
1e-6 CG stopped early and the frictionless contact of the unlocked gel chattered, force 0-0.27 N step
to step at 1 mm; Newton also holds it, at twice the time a step).

Tried and dropped: each nodal term as a fixed MuJoCo tendon (coefficients ∂J̄/∂q and spring length reset
every step, so its spring force is this gradient while the discrete integrator puts its stiffness
K V̄ c cᵀ in its effective metric). Free vibration decayed as with the element-wise flex, but in contact
CG ran at its iteration limit and the contact force swung 0-1.7 N step to step (Newton: converged
solves, the same swings, 215 ms a step); per-element tendons (no averaging) did the same, so it is the
tendon route in contact, not the averaging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

__all__ = ["NU_DEV", "MASS_FACTOR", "DAMPING_PER_S", "SOLVER_TOLERANCE", "SOLVER_ITERATIONS", "WARM_RAMP_STEPS",
           "FREE_NODES_ONLY",
           "bulk_split", "tet_volumes_and_gradients", "NodalVolume"]

NU_DEV = 0.15        # Poisson ratio left to the flex (its μ kept); the bulk stiffness beyond it is nodal. Uniform
                     # gel ν = 0.49, sphere at 1 / 3 mm: force / layer solution 1.18 / 1.23 (ν_dev = 0.3: 1.22 / 1.27,
                     # the flex's own bulk part still locks a little; 0: 1.16 / 1.21, but at ν = 0.45 the 3 mm press
                     # fell back to the followed path and ended 0.19 mm inside the sphere, instead of 0.09 mm)
MASS_FACTOR = 8.0    # the nodal forces are explicit: vertex masses × this, so that h² λ_max(M⁻¹ K_vol) = 2.2 < 4
                     # (17 at the twin's masses: the press diverged within 40 steps)
DAMPING_PER_S = 10.0  # mass-proportional damping while following a path: the unlocked gel's slow modes ring
                      # (a point load: still ±0.15 mm after 200 steps undamped, settled in ~90 with 10/s)
WARM_RAMP_STEPS = 10       # a direct solve's nodal forces ramp up over this many steps after its warm start (the
                           # twin's σ² = 10, 5 mm press: accepted in 102 steps; at once a vertex was 0.42 mm inside
                           # the tip after 4 steps and the solve was abandoned)
SOLVER_TOLERANCE = 1e-10   # MuJoCo's constraint-solver tolerance with nodal forces (1e-6 otherwise), and its
SOLVER_ITERATIONS = 300    # iteration cap (2-35 iterations a step used on the sphere press)
FREE_NODES_ONLY = True   # a tetrahedron's volume is shared by its free vertices only: a vertex bonded to the
                         # window or clamped at the rim adds no constraint (ν_dev = 0.3, 1 / 2 / 3 mm: 1.22 / 1.25 /
                         # 1.27 instead of 1.27 / 1.32 / 1.35 with every vertex)

def bulk_split(E: float, nu: float, nu_dev: float) -> tuple[float, float]:
    """Young's modulus for the flex (same μ, Poisson ``nu_dev``) and the bulk modulus left to the nodal term."""
    mu = E / (2.0 * (1.0 + nu))
    E_dev = 2.0 * mu * (1.0 + nu_dev)
    K = E / (3.0 * (1.0 - 2.0 * nu)) - E_dev / (3.0 * (1.0 - 2.0 * nu_dev))
    return E_dev, max(K, 0.0)


def tet_volumes_and_gradients(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed volumes (K,) and their gradients (K, 4, 3) of tetrahedra with vertex positions ``P`` (K, 4, 3)."""
    a, b, c = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
    g1, g2, g3 = np.cross(b, c) / 6.0, np.cross(c, a) / 6.0, np.cross(a, b) / 6.0
    vol = np.einsum("ij,ij->i", a, g1)
    return vol, np.stack([-(g1 + g2 + g3), g1, g2, g3], axis=1)


@dataclass
class NodalVolume:
    """The nodal volumetric energy of one or more materials on one mesh (positions in any consistent frame).

    Each tetrahedron's rest volume is shared equally among its *active* nodes (all four, or with ``active``
    given only those, e.g. the free vertices: a prescribed vertex carries no constraint of its own), so the
    nodal volumes V̄_n partition the body and a uniform dilation J gives U = (K/2) V (J − 1)² exactly.
    ``groups``: [(tets (K, 4), K_bulk)], one per material; a node of two materials has one term in each."""

    tets: np.ndarray            # (K, 4) the groups' tetrahedra that have an active node
    sign: np.ndarray            # (K,) orientation of the rest tetrahedra
    A: csr_matrix               # (T, K) weight of tetrahedron k in term t (1 / its number of active nodes)
    W: np.ndarray               # (T,) V̄ of the term: its share of the rest volume
    bulk: np.ndarray            # (T,) K of the term's material
    stiffness: np.ndarray       # (T,) K V̄
    term_node: np.ndarray       # (T,) mesh node of each term
    pair_term: np.ndarray       # (P,) term of each (term, node) pair of the gradient's sparsity
    pair_node: np.ndarray       # (P,) node of each pair
    G: csr_matrix               # (P, 4K) pair coefficient ∂J̄_term/∂x_node = G @ (volume gradients (4K, 3))

    @classmethod
    def build(cls, X: np.ndarray, groups, active: np.ndarray | None = None) -> "NodalVolume":
        nn = X.shape[0]
        act = np.ones(nn, bool) if active is None else np.asarray(active, bool)
        tets = np.vstack([t for t, _ in groups]).astype(np.int64)
        kb = np.concatenate([np.full(len(t), float(k)) for t, k in groups])
        gid = np.concatenate([np.full(len(t), i) for i, (t, _) in enumerate(groups)])
        na = act[tets].sum(axis=1)
        keep = na > 0
        tets, kb, gid, na = tets[keep], kb[keep], gid[keep], na[keep]
        vol, _ = tet_volumes_and_gradients(X[tets])
        sign = np.sign(vol)
        V = np.abs(vol)
        nk = len(tets)
        key = gid[:, None] * (nn + 1) + tets                                  # (K, 4) (group, node)
        on = act[tets]                                                        # (K, 4) active corners
        uniq, inv_on = np.unique(key[on], return_inverse=True)
        inv = -np.ones((nk, 4), np.int64)
        inv[on] = inv_on
        nt = len(uniq)
        kk = np.repeat(np.arange(nk)[:, None], 4, axis=1)
        A = csr_matrix(((1.0 / na)[kk[on]], (inv[on], kk[on])), shape=(nt, nk))
        W = A @ V
        kterm = np.zeros(nt)
        kterm[inv[on]] = kb[kk[on]]
        # gradient sparsity: term inv[k, j] (j active) depends on node tets[k, m] for every m of tetrahedron k
        tj = np.repeat(inv, 4, axis=1).ravel()                                # (16K,) term of (k, j, m)
        nm = np.tile(tets, (1, 4)).ravel()                                    # (16K,) node of (k, j, m)
        col = (np.arange(nk)[:, None] * 4 + np.tile(np.arange(4), 4)[None, :]).ravel()   # gradient row (k, m)
        wk = np.repeat(sign / na, 16)
        ok = tj >= 0
        tj, nm, col, wk = tj[ok], nm[ok], col[ok], wk[ok]
        pairs, pinv = np.unique(tj * (nn + 1) + nm, return_inverse=True)
        G = csr_matrix((wk / W[tj], (pinv, col)), shape=(len(pairs), 4 * nk))
        return cls(tets, sign, A, W, kterm, kterm * W, uniq % (nn + 1), pairs // (nn + 1), pairs % (nn + 1), G)

    def evaluate(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """J̄ per term (T,) and the pair coefficients ∂J̄_term/∂x_node (P, 3) at positions ``X`` (V, 3)."""
        vol, grad = tet_volumes_and_gradients(X[self.tets])
        Jbar = (self.A @ (self.sign * vol)) / self.W
        return Jbar, self.G @ grad.reshape(-1, 3)

    def energy(self, X: np.ndarray) -> float:
        Jbar, _ = self.evaluate(X)
        return float(0.5 * np.sum(self.stiffness * (Jbar - 1.0) ** 2))

    def forces(self, X: np.ndarray) -> np.ndarray:
        """Nodal forces −∂U/∂x (V, 3)."""
        Jbar, C = self.evaluate(X)
        f = -(self.stiffness * (Jbar - 1.0))[self.pair_term, None] * C
        out = np.zeros_like(X, dtype=float)
        np.add.at(out, self.pair_node, f)
        return out
