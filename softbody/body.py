"""FemBody: a mesh, a material, precomputed element matrices, state and supports.

Per-element arrays are batched over the E elements; k nodes per element. Element stiffness
K_e (E, 3k, 3k) and mass are computed once at construction by the quadratures of docs/method.md.
"""
from __future__ import annotations

import math
from functools import cache, cached_property
from typing import Callable, NamedTuple

import numpy as np
import scipy.sparse as sp

from . import kernels
from .assembly import BlockPattern, UpperAssembly
from .constitutive import LAWS
from .elements import jacobians, shape_gradients
from .errors import InvalidInputError
from .fibres import Fibres, fibre_element_matrices, fibre_matrices
from .hyperelastic import QuadratureEnergy
from .locking import check_locking
from .material import LinearElastic, Regions, isotropic_elasticity
from .mesh import Mesh
from .rotation import polar_rotation_components
from .warping import (deformation_gradient_operator, isotropic_blocks, isotropic_matrix, rest_load_operator,
                      rotated_gradient_operator, stress_map, warped_diagonal, warped_product)

Motion = Callable[[float], np.ndarray]

#: the elastic models a body takes (docs/materials.md): "warped" (the paper's stiffness-warped linear elasticity,
#: the default), "linear" (small strain, no warping: a constant matrix), and the hyperelastic laws of
#: softbody.constitutive ("corotated", "neo-hookean"), which need an iterated scheme (newton or bdf2)
MODELS = ("warped", "linear") + tuple(name for name in LAWS if name != "linear")


def strain_displacement(G: np.ndarray) -> np.ndarray:
    """B matrices (..., 6, 3k) from shape-function gradients G (..., k, 3); Voigt order xx yy zz xy yz zx."""
    *lead, k, _ = G.shape
    B = np.zeros((*lead, 6, k, 3))
    gx, gy, gz = G[..., 0], G[..., 1], G[..., 2]
    B[..., 0, :, 0] = gx
    B[..., 1, :, 1] = gy
    B[..., 2, :, 2] = gz
    B[..., 3, :, 0], B[..., 3, :, 1] = gy, gx
    B[..., 4, :, 1], B[..., 4, :, 2] = gz, gy
    B[..., 5, :, 0], B[..., 5, :, 2] = gz, gx
    return B.reshape(*lead, 6, 3 * k)


def von_mises_stress(sigma: np.ndarray) -> np.ndarray:
    """Von Mises stress (...,) [Pa] of Voigt stresses (..., 6)."""
    sx, sy, sz, txy, tyz, tzx = np.moveaxis(sigma, -1, 0)
    return np.sqrt(0.5 * ((sx - sy) ** 2 + (sy - sz) ** 2 + (sz - sx) ** 2) + 3.0 * (txy**2 + tyz**2 + tzx**2))


def _motion_positions(ids: np.ndarray, motion: Motion, t: float) -> np.ndarray:
    """motion(t) checked: (len(ids), 3) finite positions, else InvalidInputError naming the value and t."""
    try:
        p = np.asarray(motion(t), dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"prescribe: motion(t) must return ({len(ids)}, 3) positions; at t = {t:g} s: {exc}") from None
    if p.shape != (len(ids), 3):
        raise InvalidInputError(f"prescribe: motion(t) must return shape ({len(ids)}, 3), got {p.shape} at t = {t:g} s")
    bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
    if bad.size:
        raise InvalidInputError(f"prescribe: motion(t) returned non-finite positions {p[bad[:3]].tolist()} "
                                f"for nodes {ids[bad[:10]].tolist()} at t = {t:g} s; positions must be finite")
    return p


def _element_differences(fun: Callable[[np.ndarray], np.ndarray], xe: np.ndarray, rel_step: float) -> np.ndarray:
    """d fun_e / d x_e (E, 3k, 3k), node-major, of a per-element map fun (E, k, 3) -> (E, k, 3) at xe (E, k, 3), by
    central differences of step ``rel_step`` times each element's size (one column at a time over all elements)."""
    E, k, _ = xe.shape
    size = np.linalg.norm(xe - xe.mean(axis=1, keepdims=True), axis=2).max(axis=1)
    eps = (rel_step * np.maximum(size, 1e-12))[:, None, None]
    J = np.empty((E, 3 * k, 3 * k))
    for j in range(3 * k):
        d = np.zeros((E, k, 3))
        d[:, j // 3, j % 3] = 1.0
        J[:, :, j] = ((fun(xe + eps * d) - fun(xe - eps * d)) / (2 * eps)).reshape(E, -1)
    return J


def _voigt(S: np.ndarray, shear: float = 1.0) -> np.ndarray:
    """Symmetric tensors S (E, 3, 3) as Voigt rows (E, 6): xx yy zz xy yz zx, the shears times ``shear`` (2:
    engineering strain)."""
    return np.stack([S[:, 0, 0], S[:, 1, 1], S[:, 2, 2], shear * S[:, 0, 1], shear * S[:, 1, 2], shear * S[:, 2, 0]],
                    axis=1)


def _components(R: np.ndarray) -> np.ndarray:
    """Component-major (9, n) copy or view of matrices R (n, 3, 3) (a view for the arrays rotations() returns)."""
    return np.ascontiguousarray(R.reshape(len(R), 9).T)


class _Part(NamedTuple):
    """A split stiffness's second (bulk) part, stepped as an element of its own: weighted gradients (E, q, k, 3), rest
    loads K_e X_e (E, k, 3), the assembly it shares with the first part, a function giving its rotated-gradient
    operator (one-point elements, numpy path; else None), Lame parameters and their (9, 9) isotropic map."""

    gradients: np.ndarray
    rest: np.ndarray
    assembly: UpperAssembly
    rotate: Callable[[], sp.csr_matrix] | None
    lame: tuple[float, float]
    iso: np.ndarray


def _warped_upper(R9: np.ndarray, Gw: np.ndarray, P: np.ndarray, ua: UpperAssembly, rotate_grads, lame: tuple,
                  iso: np.ndarray, elements: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The warped stiffness sum_e R_e K_e R_e^T of elements with weighted gradients Gw (E, q, k, 3) and isotropic
    ``lame`` (``iso`` its (9, 9) map) as upper blocks (n_upper, 9) on ``ua``, and (compiled paths) the warped rest loads
    sum_e R_e P_e (N, 3) of P (E, k, 3) = K_e X_e (None: FemBody.rest_loads makes them); R9 (9, E) the rotations
    component-major; ``rotate_grads``: for one-point elements, a function giving their rotated_gradient_operator (made
    only on the numpy path), else None."""
    E, q, k, _ = Gw.shape
    n_nodes = ua.pattern.n_nodes
    load = None
    if rotate_grads is not None and kernels.ENABLED:  # the lines below and rest_loads, element by element
        U, load = np.zeros(9 * ua.n_upper), np.zeros((n_nodes, 3))
        kernels.warped_pairs(R9, Gw[:, 0], P, elements, ua.pairs, ua.element_scatter(), U, load)
        S = ua.with_diagonal(U.reshape(-1, 9))
    elif kernels.ENABLED:  # the Gram matrices' pairs and the rest loads, element by element
        U, load = np.zeros(9 * ua.n_upper), np.zeros((n_nodes, 3))
        kernels.warped_gram(R9, Gw, P, elements, ua.pairs, ua.element_scatter(), U, load)
        S = U.reshape(-1, 9)
    elif rotate_grads is not None:  # outer products g_a g_b^T of the node pairs a < b, (P, 3, 3, E)
        g = (rotate_grads() @ R9.reshape(-1)).reshape(k, 3, E)
        S = ua.assemble(g[ua.pairs[:, 0], :, None, :] * g[ua.pairs[:, 1], None, :, :])
    else:  # Gram matrices sum_q g_q g_q^T (E, 3k, 3k) of the rotated gradients g = Gw R^T
        RT = np.ascontiguousarray(R9[[0, 3, 6, 1, 4, 7, 2, 5, 8]].T).reshape(E, 3, 3)
        g = (Gw.reshape(E, q * k, 3) @ RT).reshape(E, q, 3 * k)
        S = ua.assemble(np.swapaxes(g, 1, 2) @ g)
    if kernels.ENABLED:  # the map in closed form, block by block (3.5x the matrix product's speed)
        K = np.empty_like(S)
        kernels.isotropic_blocks(np.ascontiguousarray(S, dtype=float), *lame, K)
    else:
        K = isotropic_blocks(S, iso)
    return K, load


class FemBody:
    """A deformable body discretised by finite elements.

    mesh: :class:`Mesh`; material: :class:`LinearElastic`; warping: stiffness warping on/off;
    damping: Rayleigh (alpha [1/s], beta [s]); damp_rigid: whether alpha M damps the body's rigid motion too
    (classic Rayleigh damping: a free body falls and spins ever slower). By default (False) alpha M acts on the
    velocity relative to the body's rigid motion (:meth:`rigid_velocity`, lagged a step): a free spin keeps its
    angular momentum and a free body falls with g / (1 + h alpha) (0.1% short at the defaults) while its vibrations
    decay as before; a body with fixed or prescribed nodes has no free rigid motion and is
    damped as classic Rayleigh. mass: "consistent" or "lumped" (HRZ diagonal scaling);
    hex_rotation: "average" (mean F of both Freudenthal inner tets) or "single" (the {0,2,5,7} tet).
    volumetric: "full" (the volumetric strain at every quadrature point) or "mean" (B-bar, hex8 only: its
    volume-weighted mean over the element; the deviatoric strain stays at every point): hex8 stops locking as nu nears
    0.5 (a cantilever within 2.5% of the converged value at nu 0.499, docs/materials.md).
    model: the elastic model (MODELS; default "warped", or "linear" when warping=False): "corotated" and
    "neo-hookean" are hyperelastic laws at the stiffness quadrature points (softbody.constitutive), stepped by
    Simulation(..., scheme="newton" or "bdf2"); their damping is the warped model's (beta on the strain rate of
    the rotated frames), so rigid motion stays undamped.
    fibres: a :class:`Fibres` reinforcement of the isotropic material along a direction per element (transversely
    isotropic; softbody.fibres), with every model.
    State: ``positions`` (N, 3) [m] and ``velocities`` (N, 3) [m/s].
    """

    def __init__(self, mesh: Mesh, material: LinearElastic, warping: bool = True,
                 damping: tuple[float, float] = (0.1, 0.001), mass: str = "consistent",
                 hex_rotation: str = "average", damp_rigid: bool = False, volumetric: str = "full",
                 model: str | None = None, fibres: Fibres | None = None):
        if not isinstance(mesh, Mesh):
            raise InvalidInputError(f"mesh must be a softbody.Mesh, got {type(mesh).__name__}")
        if not isinstance(material, (LinearElastic, Regions)):
            raise InvalidInputError(f"material must be a softbody.LinearElastic or softbody.Regions, got "
                                    f"{type(material).__name__}")
        if mass not in ("consistent", "lumped"):
            raise InvalidInputError(f"mass must be 'consistent' or 'lumped', got {mass!r}")
        if hex_rotation not in ("average", "single"):
            raise InvalidInputError(f"hex_rotation must be 'average' or 'single', got {hex_rotation!r}")
        if volumetric not in ("full", "mean"):
            raise InvalidInputError(f"volumetric must be 'full' or 'mean' (B-bar), got {volumetric!r}")
        if model is None:
            model = "warped" if warping else "linear"
        if model not in MODELS:
            raise InvalidInputError(f"model must be one of {MODELS}, got {model!r}")
        if not warping and model != "linear":
            raise InvalidInputError(f"warping=False is the model 'linear'; model={model!r} turns with the body (give "
                                    "one of the two)")
        law = LAWS[model] if model not in ("warped", "linear") else None
        if law is not None and volumetric != "full":
            raise InvalidInputError(f"volumetric={volumetric!r} (B-bar) is for the linear models; model {model!r} "
                                    "takes the volumetric strain at every quadrature point (use tet10 elements "
                                    "near nu = 0.5)")
        if fibres is not None and not isinstance(fibres, Fibres):
            raise InvalidInputError(f"fibres must be a softbody.Fibres or None, got {type(fibres).__name__}")
        if volumetric == "mean" and mesh.element_type.name != "hex8":
            raise InvalidInputError(f"volumetric='mean' (B-bar) is for hex8 elements, got {mesh.element_type.name}: a "
                                    "tet4's one quadrature point is its own mean, and a tet10's mean dilatation relaxes "
                                    "it too far (a cantilever 1.6x too soft); tet10 does not lock as it is "
                                    "(docs/materials.md)")
        try:
            alpha, beta = (float(d) for d in damping)
        except (TypeError, ValueError):
            raise InvalidInputError(f"damping must be a pair (alpha, beta), got {damping!r}") from None
        if not (np.isfinite([alpha, beta]).all() and alpha >= 0 and beta >= 0):
            raise InvalidInputError(f"Rayleigh damping (alpha, beta) must be finite and >= 0, got {damping!r}")
        self.mesh = mesh
        self.material = material
        self.model = model
        self.law = law  # the hyperelastic law (softbody.constitutive), None for the linear models' fast paths
        self.warping = model != "linear"  # the element rotations: the warped model's, and the others' damping frames
        self.damping = (alpha, beta)
        self.damp_rigid = bool(damp_rigid)
        self.mass_kind = mass
        self.hex_rotation = hex_rotation
        self.volumetric = volumetric
        et = mesh.element_type
        self.element_type = et
        X = mesh.nodes[mesh.elements]  # (E, k, 3)
        E, k = mesh.elements.shape
        regions = isinstance(material, Regions)
        for m in material.materials if regions else (material,):
            D = np.asarray(m.elasticity_matrix(), dtype=float)
            if D.shape != (6, 6) or not np.allclose(D, isotropic_elasticity(*m.lame), rtol=1e-12, atol=0.0):
                raise InvalidInputError(f"material {type(m).__name__}: its elasticity matrix is not the isotropic "
                                        "(6, 6) one of its Lame parameters, which the warped step uses (give a "
                                        "LinearElastic; fibres: FemBody(..., fibres=softbody.Fibres(directions, "
                                        "modulus)))")
        if regions:
            if len(material.labels) != E:
                raise InvalidInputError(f"Regions labels: one per element, {E}, got {len(material.labels)}")
            lam, mu = material.lame  # (E,) each
            nu_most = material.largest_nu
        else:
            lam, mu = material.lame
            nu_most = material.nu
        if volumetric == "full":
            check_locking(et.name, nu_most, bbar=law is None)

        self.pattern = BlockPattern.from_elements(mesh.elements, mesh.n_nodes)

        # stiffness: K_e = sum_q w_q detJ_q B_q^T D B_q
        xi, w = et.stiffness_rule
        G, detJ = shape_gradients(et, X, xi)
        sqrt_w = np.sqrt(detJ * w)
        # weighted gradients sqrt(w_q detJ_q) dN/dX (E, q, k, 3) and the operators that rotate them and
        # give the warped rest loads, for the step's warped stiffness and forces (warped_stiffness_blocks)
        Gw = G * sqrt_w[:, :, None, None]
        mean = volumetric == "mean"
        # split: the shear part (mu, at every point) and the bulk part (kappa = lam + 2 mu / 3: at every point, or
        # B-bar's on the mean gradients) apart, each a scaled-gradient "element" of its own: K = kappa S + mu (S^T +
        # tr(S) I - 2/3 S), both weights positive, per element (regions) or B-bar's
        split = mean or regions
        if split:
            lam_e, mu_e = np.broadcast_to(lam, (E,)), np.broadcast_to(mu, (E,))
            kappa_e = lam_e + 2.0 * mu_e / 3.0
            if mean:  # B-bar: the volumetric strain's volume-weighted mean over the element
                volume = (detJ * w).sum(axis=1)  # (E,)
                g_mean = np.einsum("eq,eqka->eka", detJ * w, G) / volume[:, None, None]  # (E, k, 3)
                g1 = (np.sqrt(kappa_e * volume)[:, None, None] * g_mean)[:, None]  # (E, 1, k, 3)
                P1 = 3.0 * (kappa_e * volume)[:, None, None] * g_mean
            else:
                g1 = Gw * np.sqrt(kappa_e)[:, None, None, None]
                P1 = 3.0 * kappa_e[:, None, None] * np.einsum("eq,eqka->eka", sqrt_w, Gw)
            Gw = Gw * np.sqrt(mu_e)[:, None, None, None]
            lam, mu = -2.0 / 3.0, 1.0  # the shear part's, on gradients scaled by sqrt(mu_e)
        self._Gw = Gw
        # fibres: (directions (E, 3), the scalar factors M_e (E, k, k), M_e (X_e . a) (E, k)): softbody.fibres
        self.fibres = fibres
        self._fibre = None
        if fibres is not None:
            a, Ef = fibres.per_element(E)
            Mf = fibre_matrices(G, detJ * w, a, Ef)
            self._fibre = (a, Mf, np.einsum("ekl,el->ek", Mf, np.einsum("elc,ec->el", X, a)))
        # a hyperelastic law's energy at the same quadrature points (its own lam and mu: the split above rescales)
        self._hyper = None if law is None else QuadratureEnergy(
            law, G, detJ * w, *material.lame, fibres=None if fibres is None else fibres.per_element(E))
        # warped stiffness: assembled over the node pairs a <= b only (UpperAssembly), from the outer
        # products of component-major rotated gradients for one-point elements (tet4), else from whole
        # Gram matrices per element (one batched matmul)
        self._rotate_grads = None  # one-point elements: the function giving their operator (numpy path), made at first use
        if self._Gw.shape[1] == 1:
            self._upper = UpperAssembly.from_elements(self.pattern, mesh.elements, "pairs")
            self._rotate_grads = cache(lambda: rotated_gradient_operator(Gw))  # not self: no reference cycle
        else:
            self._upper = UpperAssembly.from_elements(self.pattern, mesh.elements, "matrices")
        self._isotropic = isotropic_matrix(lam, mu)  # (9, 9) map from Gram to stiffness blocks
        self._lame = (lam, mu)
        P = (3.0 * lam + 2.0 * mu) * np.einsum("eq,eqka->eka", sqrt_w, self._Gw)  # K_e X_e, (E, k, 3)
        self._rest_P = np.ascontiguousarray(P)  # for kernels.warped_pairs and warped_gram
        # the bulk part of a split stiffness, assembled beside the first (lame (1, 0) on its scaled gradients)
        self._bulk_part = None
        if split:
            # on the first part's assembly: "pairs" (tet4: both parts one-point) or "matrices" (Gram matrices of any
            # number of points: B-bar's one-point part too)
            self._bulk_part = _Part(np.ascontiguousarray(g1), np.ascontiguousarray(P1), self._upper,
                                    cache(lambda: rotated_gradient_operator(g1)) if self._rotate_grads is not None
                                    else None, (1.0, 0.0), isotropic_matrix(1.0, 0.0))
            if mean:  # the mean divergence rows (E, 3k), for B-bar's strain output
                self._mean_divergence = g_mean.reshape(E, 3 * k)
        self._elements_c = np.ascontiguousarray(mesh.elements, dtype=np.int64)  # for kernels.warped_product

        # mass: scalar element matrices (E, k, k), the 3x3 blocks are multiples of I3 (not kept: Me makes them again)
        Me = self._element_masses()
        # characteristic tetrahedra for the warping rotation: the operator of their deformation gradients
        ct = et.char_tets if (et.name != "hex8" or hex_rotation == "average") else et.char_tets[:1]
        self.char_tets = ct
        Xc = X[:, ct]  # (E, c, 4, 3)
        Dm = np.swapaxes(Xc[:, :, 1:] - Xc[:, :, :1], -1, -2)  # columns X2-X1, X3-X1, X4-X1
        Dm_inv = np.linalg.inv(Dm)
        # F = mean over the c tets of Ds Dm^-1 = sum_a x_a g_a^T over their nodes, with the linear-tet
        # gradients g_a (rows of Dm^-1, and minus their sum for the first node) divided by c
        gc = np.concatenate([-Dm_inv.sum(axis=2, keepdims=True), Dm_inv], axis=2) / len(ct)
        self._char_grads = gc.reshape(E, -1, 3)  # (E, 4c, 3), on the element's local nodes ct.reshape(-1)
        local = ct.reshape(-1)
        self._char_nodes = (self._elements_c if np.array_equal(local, np.arange(mesh.elements.shape[1]))  # (tet4)
                            else np.ascontiguousarray(mesh.elements[:, local], dtype=np.int64))  # (E, 4c) global

        # gradients at the element centre for strain and stress output
        Gc, _ = shape_gradients(et, X, et.centroid[None])
        self._Gc = Gc[:, 0]  # (E, k, 3); the strain from them directly (no (E, 6, 3k) B matrices kept)
        if self._Gc.shape == self._char_grads.shape and np.array_equal(self._Gc, self._char_grads):
            self._Gc = self._char_grads  # (tet4: the element is its characteristic tetrahedron; one copy, not two)
        # the elasticity matrix (6, 6), or per element (E, 6, 6) for regions, for stress output
        self.D = (np.array([isotropic_elasticity(*m.lame) for m in material.materials])[material.labels] if regions
                  else material.elasticity_matrix())

        self.M_data = self.pattern.assemble_scalar(Me)  # (nnzb,)
        self._mass_upper = self.M_data[self._upper.upper]  # (n_upper,) on the upper blocks
        n = mesh.n_nodes
        self._mass_csr = sp.csr_matrix((self.M_data, self.pattern.indices, self.pattern.indptr), shape=(n, n))
        Ek = mesh.elements.size
        # sums per-element rows (E, m) into nodes (N, m)
        self._incidence = sp.csr_matrix((np.ones(Ek), (mesh.elements.ravel(), np.repeat(np.arange(E), k))),
                                        shape=(n, E))
        self.node_mass = np.bincount(mesh.elements.ravel(), weights=Me.sum(axis=2).ravel(),
                                     minlength=mesh.n_nodes)  # row sums: consistent gravity load / g

        self.rest = mesh.nodes.copy()
        self.positions = mesh.nodes.copy()
        self.velocities = np.zeros_like(self.positions)
        self.fixed = np.zeros(mesh.n_nodes, dtype=bool)
        self._used = mesh.used_nodes()
        self.fixed[~self._used] = True  # unused nodes carry no mass: hold them at rest
        self.prescribed: list[tuple[np.ndarray, Motion]] = []

    def _element_masses(self) -> np.ndarray:
        """The scalar element mass matrices (E, k, k) [kg] (consistent, or HRZ-lumped), and ``volumes`` (E,) [m^3]."""
        et, mesh = self.element_type, self.mesh
        X = mesh.nodes[mesh.elements]  # (E, k, 3)
        E, k = mesh.elements.shape
        xim, wm = et.mass_rule
        detJm = np.linalg.det(jacobians(et, X, xim))  # (E, q): the mass needs no gradients
        N = et.shape(xim)
        density = np.broadcast_to(self.material.density, (E,))
        Me = density[:, None, None] * np.einsum("eq,qa,qb->eab", detJm * wm, N, N, optimize=True)
        self.volumes = detJm @ wm
        if self.mass_kind == "lumped":  # HRZ: diagonal scaled to the element mass; positive for every element type
            d = np.einsum("eaa->ea", Me)
            d *= (density * self.volumes / d.sum(axis=1))[:, None]
            Me = np.einsum("ea,ab->eab", d, np.eye(k))
        return Me

    @property
    def Me(self) -> np.ndarray:
        """The scalar element mass matrices (E, k, k) [kg], each 3x3 block a multiple of I3 (made on each call: the
        step reads the assembled M_data; 40 MB at 330k tet4 elements)."""
        return self._element_masses()

    @property
    def M_blocks(self) -> np.ndarray:
        """The consistent (or lumped) mass matrix as block data (nnzb, 3, 3), each block a multiple of I3 (made on
        each call from M_data (nnzb,): the step reads M_data and its upper part, not these)."""
        return self.M_data[:, None, None] * np.eye(3)

    # ------------------------------------------------------------------ state
    @property
    def positions(self) -> np.ndarray:
        """Node positions (N, 3) [m]. Assigning an array checks its shape and that it is finite (in-place
        writes such as ``body.positions[ids] = ...`` are the caller's responsibility)."""
        return self._positions

    @positions.setter
    def positions(self, value) -> None:
        self._positions = self._node_array(value, "positions", "[m]")

    @property
    def velocities(self) -> np.ndarray:
        """Node velocities (N, 3) [m/s]; assigning checks shape and finiteness as for ``positions``."""
        return self._velocities

    @velocities.setter
    def velocities(self, value) -> None:
        self._velocities = self._node_array(value, "velocities", "[m/s]")

    def _node_array(self, value, name: str, unit: str) -> np.ndarray:
        """``value`` as a float (N, 3) array (no copy if it is one), or InvalidInputError naming the bad nodes."""
        shape = (self.mesh.n_nodes, 3)
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"{name} must be a {shape} array of numbers {unit}, got {type(value).__name__}") from None
        if a.shape != shape:
            raise InvalidInputError(f"{name} must have shape {shape} (one row per node) {unit}, got {a.shape}")
        if not math.isfinite(float(np.add.reduce(a, axis=None))) and not np.isfinite(a).all():  # (a finite sum: all are)
            bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
            raise InvalidInputError(f"{name} must be finite {unit}: nodes {bad[:5].tolist()}{' ...' if bad.size > 5 else ''} "
                                    f"({bad.size} of {shape[0]}) are not, e.g. node {bad[0]} = {a[bad[0]].tolist()}")
        return a

    # ------------------------------------------------------------------ sizes
    @property
    def n_nodes(self) -> int:
        return self.mesh.n_nodes

    @property
    def n_dofs(self) -> int:
        return 3 * self.mesh.n_nodes

    @cached_property
    def _char_F(self) -> sp.csr_matrix:
        """The characteristic tetrahedra's deformation-gradient operator (numpy path of char_gradients; made at first
        use: the compiled path works on _char_nodes and _char_grads)."""
        return deformation_gradient_operator(self._char_nodes, self._char_grads, self.mesh.n_nodes)

    @cached_property
    def _rest_load(self) -> sp.csr_matrix:
        """The warped rest loads' operator (numpy path of rest_loads; made at first use: the compiled assembly gives
        the loads with the stiffness)."""
        return rest_load_operator(self.mesh.elements, self.rest_element_loads, self.mesh.n_nodes)

    @property
    def rest_element_loads(self) -> np.ndarray:
        """K_e X_e per element (E, k, 3) [N] (the rest loads before assembly, of every part of the stiffness)."""
        loads = self._rest_P if self._bulk_part is None else self._rest_P + self._bulk_part.rest
        if self._fibre is not None:
            a, _, p = self._fibre
            loads = loads + p[:, :, None] * a[:, None, :]
        return loads

    @cached_property
    def Ke(self) -> np.ndarray:
        """Element stiffness matrices K_e (E, 3k, 3k) [N/m] (interleaved dofs), sum_q w detJ B^T D B over each part of
        the stiffness (a split one: shear and bulk): made at first use (the static solve, the Newton scheme, the
        elastic energy), not by the warped step, which works on the gradients (E * (3k)^2 doubles: 1.2 kB per tet4
        element)."""
        parts = [(self._Gw, self._lame)]
        if self._bulk_part is not None:
            parts.append((self._bulk_part.gradients, self._bulk_part.lame))
        Ke = None
        for Gw, lame in parts:
            B = strain_displacement(Gw)  # weighted: sqrt(w detJ) B (E, q, 6, 3k)
            part = np.einsum("eqia,ij,eqjb->eab", B, isotropic_elasticity(*lame), B, optimize=True)
            Ke = part if Ke is None else Ke + part
        if self._fibre is not None:
            a, Mf, _ = self._fibre
            Ke = Ke + fibre_element_matrices(Mf, a)
        Ke = 0.5 * (Ke + Ke.transpose(0, 2, 1))
        Ke.flags.writeable = False
        return Ke

    @property
    def total_mass(self) -> float:
        return float(np.sum(self.material.density * self.volumes))

    def part_offsets(self) -> np.ndarray:
        """Offsets (k + 1,) of the node ranges that move as bodies of their own: here the whole body; a BodyStack's
        members."""
        return np.array([0, len(self._positions)])

    def rigid_parts(self) -> tuple[np.ndarray, np.ndarray]:
        """The node ranges that move as bodies (:meth:`part_offsets`) and whether each is free (k,) bool: no fixed or
        prescribed node of its elements (nodes no element uses are held at rest, and do not count), so that its
        rigid motion is its own."""
        parts = self.part_offsets()
        fixed = self.fixed & self._used
        if not self.prescribed and not fixed[fixed.argmax()]:  # no support at all (argmax: one C call, no wrapper)
            free = np.empty(len(parts) - 1, dtype=bool)
            free.fill(True)
            return parts, free
        return parts, ~np.logical_or.reduceat(self.supported() & self._used, parts[:-1])

    def rigid_velocity(self, momenta: np.ndarray, parts: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The rigid velocity field (N, 3) [m/s] with the linear and angular momentum of the nodal momenta
        ``momenta`` (N, 3) [kg m/s] (e.g. M v) under the mass matrix, part by part (``parts``: :meth:`rigid_parts`,
        if at hand; zero on parts that are not free): V + omega x (x - c), c the part's centre of mass, V = P / m
        and (Phi_r^T M Phi_r) omega = L, the inertia tensor taken with the body's own mass matrix (a rigid field is
        its own fit, consistent mass or lumped)."""
        parts, free = self.rigid_parts() if parts is None else parts
        x, m = self._positions, self.node_mass
        if kernels.ENABLED:  # the same arithmetic part by part (softbody.kernels)
            k, n = len(parts) - 1, len(x)
            mass, P, L = np.empty(k), np.empty((k, 3)), np.empty((k, 3))
            r, Mr, out = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
            kernels.part_moments(parts, x, m, np.ascontiguousarray(momenta, dtype=float), mass, P, L, r)
            M = self._mass_csr
            kernels.scalar_product(M.indptr, M.indices, M.data, r, Mr)
            kernels.rigid_field(parts, free, r, Mr, mass, P, L, out)
            return out
        starts, count = parts[:-1], np.diff(parts)
        mass = np.add.reduceat(m, starts)
        c = np.add.reduceat(m[:, None] * x, starts) / mass[:, None]
        r = x - np.repeat(c, count, axis=0)
        Mr = self.mass_product(r)  # M has no entries between parts (the members of a stack)
        S = np.add.reduceat(r[:, :, None] * Mr[:, None, :], starts)  # sum_ij m_ij r_i r_j^T, (k, 3, 3)
        inertia = np.trace(S, axis1=1, axis2=2)[:, None, None] * np.eye(3) - np.swapaxes(S, 1, 2)
        V = np.add.reduceat(momenta, starts) / mass[:, None]
        omega = np.linalg.solve(inertia, np.add.reduceat(np.cross(r, momenta), starts)[:, :, None])[:, :, 0]
        V[~free] = 0.0
        omega[~free] = 0.0
        return np.repeat(V, count, axis=0) + np.cross(np.repeat(omega, count, axis=0), r)

    def rigid_damping_relief(self, h: float, momenta: np.ndarray) -> np.ndarray | None:
        """What a step of size h [s] adds to the right-hand side so that alpha M damps the velocity relative to the
        rigid motion, not the rigid motion (see the class doc): h alpha M v_r (N, 3) [kg m/s], v_r the rigid field
        of ``momenta`` (M v at the start of the step: zero at rest, so a body resting on a support or hanging from
        an attachment feels nothing of it); None where nothing is spared (damp_rigid, no alpha, or no free
        part)."""
        alpha = self.damping[0]
        if self.damp_rigid or alpha == 0.0:
            return None
        parts = self.rigid_parts()
        free = parts[1]
        if not free[free.argmax()]:
            return None
        return (h * alpha) * self.mass_product(self.rigid_velocity(momenta, parts))

    # ------------------------------------------------------------------ supports
    def _node_ids(self, node_ids, what: str) -> np.ndarray:
        ids = np.atleast_1d(np.asarray(node_ids))
        if ids.dtype == bool:
            if ids.shape != (self.n_nodes,):
                raise InvalidInputError(f"{what}: a boolean mask needs shape ({self.n_nodes},), got {ids.shape}")
            ids = np.flatnonzero(ids)
        if ids.size and not np.issubdtype(ids.dtype, np.integer):
            raise InvalidInputError(f"{what}: node ids must be integers, got dtype {ids.dtype}")
        ids = ids.astype(np.int64)
        bad = ids[(ids < 0) | (ids >= self.n_nodes)]
        if bad.size:
            raise InvalidInputError(f"{what}: node ids {bad[:10].tolist()} do not exist; valid ids are 0..{self.n_nodes - 1}")
        return np.unique(ids)

    def fix(self, node_ids) -> None:
        """Hold nodes (ids or boolean mask) at their current positions, exactly."""
        ids = self._node_ids(node_ids, "fix")
        self.fixed[ids] = True
        self.velocities[ids] = 0.0

    def prescribe(self, node_ids, motion: Motion) -> None:
        """Make nodes follow ``motion(t)`` -> (len(ids), 3) positions [m] exactly (reached at the end of each step)."""
        ids = self._node_ids(node_ids, "prescribe")
        if not callable(motion):
            raise InvalidInputError("prescribe: motion must be a function of time returning (n, 3) positions")
        _motion_positions(ids, motion, 0.0)
        self.prescribed.append((ids, motion))

    def supported(self) -> np.ndarray:
        """Boolean mask (N,) of nodes held by fix() or prescribe()."""
        mask = self.fixed.copy()
        for ids, _ in self.prescribed:
            mask[ids] = True
        return mask

    def constrained_targets(self, t_next: float, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Nodes held by supports and the velocities (m, 3) that bring them exactly to their
        positions at time t_next after a step h. Later prescriptions override earlier ones and fixes."""
        if not self.prescribed and not self.fixed.any():
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        target = np.full((self.n_nodes, 3), np.nan)
        target[self.fixed] = 0.0
        for ids, motion in self.prescribed:
            p = _motion_positions(ids, motion, t_next)
            target[ids] = (p - self.positions[ids]) / h
        nodes = np.flatnonzero(~np.isnan(target[:, 0]))
        return nodes, target[nodes]

    # ------------------------------------------------------------------ warping
    def rotations(self, x: np.ndarray | None = None) -> np.ndarray:
        """Warping rotation R_e (E, 3, 3) of each element from its characteristic tetrahedra (identity if warping is off).

        The last result is remembered, keyed by an exact copy of the positions, so that a recorder or
        a stress query between steps and the next step's start share one polar decomposition. The
        returned array is a read-only view of the component-major (9, E) result.
        """
        E = self.mesh.n_elements
        if not self.warping:
            return np.broadcast_to(np.eye(3), (E, 3, 3))
        x = self.positions if x is None else x
        key = self.__dict__.get("_rotation_key")
        if key is not None and key.shape == x.shape and np.array_equal(key, x):
            return self._rotation_value
        R9 = polar_rotation_components(self.characteristic_gradient(x))
        R9.flags.writeable = False
        R = R9.T.reshape(E, 3, 3)
        self._rotation_key, self._rotation_value = np.array(x, dtype=float), R
        return R

    def characteristic_gradient(self, x: np.ndarray) -> np.ndarray:
        """Deformation gradients of the elements' characteristic tetrahedra (hex8 "average": the mean
        of its two) at positions x (N, 3), component-major (9, E): row 3 i + j holds F_ij. (Taken of
        x minus its mean: each tet's gradients sum to zero, and so an offset adds no round-off.)"""
        x = np.asarray(x, dtype=float)
        if kernels.ENABLED:  # element by element, the mean in the same call (softbody.kernels)
            out = np.empty((9, self.mesh.n_elements))
            kernels.characteristic_gradients(self._char_nodes, self._char_grads, np.ascontiguousarray(x), out)
            return out
        return (self._char_F @ (x - x.mean(axis=0)).reshape(-1)).reshape(9, -1)

    def local_displacements(self, x: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Unrotated element displacements R^T x_e - X_e, (E, 3k)."""
        xe = x[self.mesh.elements]  # (E, k, 3)
        return (xe @ R).reshape(len(xe), -1) - self.rest[self.mesh.elements].reshape(len(xe), -1)

    def element_forces(self, x: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Elastic forces on each element's nodes, -R K_e (R^T x_e - X_e), shape (E, k, 3) [N]."""
        return -self._rotated_product(self.local_displacements(x, R), R)

    def _rotated_product(self, local: np.ndarray, R: np.ndarray) -> np.ndarray:
        """R_e K_e local_e for local (E, 3k); returns (E, k, 3)."""
        E, k = self.mesh.elements.shape
        fl = (self.Ke @ local[:, :, None]).reshape(E, k, 3)
        return fl @ np.swapaxes(R, 1, 2)

    def mass_product(self, y: np.ndarray) -> np.ndarray:
        """M y for y (N, 3); returns (N, 3)."""
        if kernels.ENABLED and (y.ndim == 2 and y.shape[1] == 3 if isinstance(y, np.ndarray) else
                                np.ndim(y) == 2 and np.shape(y)[1] == 3):  # row by row, compiled (softbody.kernels)
            M, out = self._mass_csr, np.empty((len(self._positions), 3))
            kernels.scalar_product(M.indptr, M.indices, M.data, np.ascontiguousarray(y, dtype=float), out)
            return out
        return self._mass_csr @ y

    def node_frames(self, R: np.ndarray) -> np.ndarray:
        """Per-node rotations (N, 3, 3) close to the mean of the adjacent elements' R_e (E, 3, 3), for
        conjugating a preconditioner: Gram-Schmidt of the first two columns of their sum S. A third of
        the cost of S's polar factor and equal to it when the R_e agree; on the tet10 (9,9,2) sheet the
        PCG needed 1% more iterations than with the polar factor. Nodes whose S is nearly singular
        (adjacent elements turned far apart) get the polar factor."""
        S9 = np.ascontiguousarray((self._incidence @ R.reshape(len(R), 9)).T)  # (9, N)
        if kernels.ENABLED:  # the same arithmetic node by node (softbody.kernels)
            Q, bad = np.empty((S9.shape[1], 3, 3)), np.empty(S9.shape[1], dtype=bool)
            kernels.node_frames(S9, Q, bad)
            if bad.any():
                Q[bad] = polar_rotation_components(S9[:, bad]).T.reshape(-1, 3, 3)
            return Q
        a, b = S9[[0, 3, 6]], S9[[1, 4, 7]]  # columns 0 and 1 of every S, (3, N)
        na = np.sqrt(np.einsum("in,in->n", a, a))
        a = a / np.where(na > 0, na, 1.0)
        b = b - np.einsum("in,in->n", a, b) * a
        nb = np.sqrt(np.einsum("in,in->n", b, b))
        b = b / np.where(nb > 0, nb, 1.0)
        Q = np.empty((S9.shape[1], 3, 3))
        Q[:, :, 0], Q[:, :, 1] = a.T, b.T
        Q[:, 0, 2] = a[1] * b[2] - a[2] * b[1]  # a x b (np.cross's general machinery costs several times more)
        Q[:, 1, 2] = a[2] * b[0] - a[0] * b[2]
        Q[:, 2, 2] = a[0] * b[1] - a[1] * b[0]
        scale = 1e-3 * np.sqrt(np.einsum("kn,kn->n", S9, S9))  # |S| is about sqrt(3) x adjacent elements
        bad = (na <= scale) | (nb <= scale)
        if bad.any():
            Q[bad] = polar_rotation_components(S9[:, bad]).T.reshape(-1, 3, 3)
        return Q

    def elastic_forces(self, x: np.ndarray | None = None) -> np.ndarray:
        """Global elastic forces (N, 3) [N] at positions x (default: current): warped if warping is on, minus the
        energy's gradient for a hyperelastic model."""
        x = self.positions if x is None else np.asarray(x, dtype=float)
        if x.shape != self.positions.shape:
            raise InvalidInputError(f"positions must have shape {self.positions.shape}, got {x.shape}")
        if self._hyper is not None:
            return -self.scatter_nodal(self._hyper.gradients(x[self.mesh.elements]))
        return self.scatter_nodal(self.element_forces(x, self.rotations(x)))

    def energy_gradient(self, x: np.ndarray, R: np.ndarray | None = None) -> np.ndarray:
        """The exact gradient dPsi/dx (N, 3) [N] of the strain energy (``elastic_energy``): the warped one
        Psi(x) = 1/2 sum_e u_e^T K_e u_e with R_e the polar rotation of the characteristic tetrahedra at x (R: those
        rotations, if at hand), or the hyperelastic model's; see :meth:`element_energy_gradients`."""
        x = np.asarray(x, dtype=float)
        if R is None and self._hyper is None:  # (a hyperelastic energy needs no rotations)
            R = self.rotations(x)
        return self.scatter_nodal(self.element_energy_gradients(x[self.mesh.elements], R))

    def element_energy_gradients(self, xe: np.ndarray, R: np.ndarray | None = None) -> np.ndarray:
        """dPsi_e/dx_e (E, k, 3) [N] of each element's strain energy at its node positions xe (E, k, 3): the
        model's (a hyperelastic law's, softbody.hyperelastic), or the warped energy's (:meth:`warped_energy_gradients`,
        R the rotations at xe if at hand)."""
        if self._hyper is not None:
            return self._hyper.gradients(xe)
        return self.warped_energy_gradients(xe, R)

    def warped_energy_gradients(self, xe: np.ndarray, R: np.ndarray | None = None,
                                offset: np.ndarray | None = None) -> np.ndarray:
        """dPsi_e/dx_e (E, k, 3) [N] of each element's warped strain energy at its node positions xe (E, k, 3);
        offset (E, 3k) [m]: measure the unrotated displacement from it, u_e = R^T x_e - X_e - offset_e (the Newton
        scheme's damping: the strain since the start of the step).

        It is R_e K_e u_e (minus the warped forces) plus the change of R_e itself: with Y_e = sum_a x_a
        (K_e u_e)_a^T, S = R^T F, z = (tr(S) I - S)^-1 axial(skew(R^T Y)), the energy's derivative by the
        characteristic gradient F is 2 R [z]x, which reaches the nodes through F = sum_b x_b g_b^T. For a
        linear tet R^T Y is symmetric and the second part vanishes (the warped force is the gradient); for
        tet10 and hex8, whose rotation is their characteristic tet's, it does not. Where an element is so
        inverted that tr(S) I - S is singular, its rotation's share is left out."""
        E, k = self.mesh.elements.shape
        ct = self.char_tets.reshape(-1)
        F = np.einsum("eci,ecj->eij", xe[:, ct], self._char_grads)
        if R is None:
            R = polar_rotation_components(_components(F)).T.reshape(E, 3, 3) if self.warping else \
                np.broadcast_to(np.eye(3), (E, 3, 3))
        u = (xe @ R).reshape(E, -1) - self.rest[self.mesh.elements].reshape(E, -1)
        if offset is not None:
            u = u - offset
        fh = (self.Ke @ u[:, :, None]).reshape(E, k, 3)  # K_e u_e, unrotated
        grad = fh @ np.swapaxes(R, 1, 2)
        if not self.warping:
            return grad
        Y = np.einsum("eka,ekb->eab", xe - xe.mean(axis=1, keepdims=True), fh)  # (K u sums to zero)
        B = np.swapaxes(R, 1, 2) @ Y
        y = 0.5 * np.stack([B[:, 2, 1] - B[:, 1, 2], B[:, 0, 2] - B[:, 2, 0], B[:, 1, 0] - B[:, 0, 1]], axis=1)
        S = np.swapaxes(R, 1, 2) @ F
        trS = np.trace(S, axis1=1, axis2=2)
        T = trS[:, None, None] * np.eye(3) - S
        ok = np.abs(np.linalg.det(T)) > 1e-12 * np.abs(trS) ** 3
        z = np.zeros((E, 3))
        z[ok] = np.linalg.solve(T[ok], y[ok][:, :, None])[:, :, 0]
        zx = np.zeros((E, 3, 3))
        zx[:, 0, 1], zx[:, 0, 2], zx[:, 1, 2] = -z[:, 2], z[:, 1], -z[:, 0]
        zx -= np.swapaxes(zx, 1, 2)
        P = 2.0 * R @ zx  # dPsi/dF of each element's rotation
        grad[:, ct] += np.einsum("eij,ecj->eci", P, self._char_grads)  # (the characteristic nodes are distinct)
        return grad

    def energy_hessian_blocks(self, x: np.ndarray, rel_step: float = 1e-6, project: bool = True) -> np.ndarray:
        """The exact Hessian of the strain energy at x (N, 3), assembled as block data (nnzb, 3, 3) [N/m], made
        positive semi-definite (project=False keeps the negative eigenvalues). A hyperelastic model's: analytic,
        each quadrature point's tangent projected. The warped energy's: rotations' derivatives included, per
        element by central differences of :meth:`element_energy_gradients` (step ``rel_step`` times the element's
        size), symmetrised, each element's projected: a tangent for Newton's method that knows how the rotations
        turn (the warped stiffness K' does not)."""
        xe = np.asarray(x, dtype=float)[self.mesh.elements]
        if self._hyper is not None:
            return self.pattern.assemble(self._hyper.hessians(xe, project))
        H = _element_differences(self.element_energy_gradients, xe, rel_step)
        H = 0.5 * (H + np.swapaxes(H, 1, 2))
        if project:
            lam, V = np.linalg.eigh(H)
            H = (V * np.maximum(lam, 0.0)[:, None, :]) @ np.swapaxes(V, 1, 2)
        return self.pattern.assemble(H)

    def warped_force_jacobian_blocks(self, x: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
        """-d f_w / dx of the warped elastic forces f_w = -sum_e R_e K_e (R_e^T x_e - X_e) at x (N, 3), the
        rotations' change included, as block data (nnzb, 3, 3) [N/m] (not symmetric: the warped force is not quite a
        gradient). Per element by central differences (step ``rel_step`` times the element's size) of its forces with
        its rotation re-evaluated; for Newton's method on the warped step's force balance (solve_equilibrium)."""
        xe = np.asarray(x, dtype=float)[self.mesh.elements]
        E, k, _ = xe.shape
        ct = self.char_tets.reshape(-1)
        X = self.rest[self.mesh.elements].reshape(E, -1)

        def forces(y: np.ndarray) -> np.ndarray:  # -R K (R^T y - X) per element, R of the element at y
            F = np.einsum("eci,ecj->eij", y[:, ct], self._char_grads)
            R = polar_rotation_components(_components(F)).T.reshape(E, 3, 3)
            u = (y @ R).reshape(E, -1) - X
            return -((self.Ke @ u[:, :, None]).reshape(E, k, 3) @ np.swapaxes(R, 1, 2))

        return self.pattern.assemble(-_element_differences(forces, xe, rel_step))

    @cached_property
    def _scatter(self) -> sp.csr_matrix:
        """The (N, E*k) 0/1 matrix summing element-node rows into nodes (made at first use: the warped step's compiled
        kernels sum in place)."""
        Ek = self.mesh.elements.size
        return sp.csr_matrix((np.ones(Ek), (self.mesh.elements.ravel(), np.arange(Ek))), shape=(self.n_nodes, Ek))

    def scatter_nodal(self, fe: np.ndarray) -> np.ndarray:
        """Sum per-element nodal vectors (E, k, 3) into (N, 3)."""
        return self._scatter @ fe.reshape(-1, 3)

    def warped_stiffness(self, R: np.ndarray | None) -> np.ndarray:
        """Element stiffness matrices R_e K_e R_e^T (E, 3k, 3k), R_e block-diagonal; K_e when R is None."""
        if R is None or not self.warping:
            return self.Ke
        E, n, _ = self.Ke.shape
        Rb = np.zeros((E, n, n))  # block-diagonal R: dense batched matmuls beat many 3x3 products
        for a in range(n // 3):
            Rb[:, 3 * a:3 * a + 3, 3 * a:3 * a + 3] = R
        return Rb @ self.Ke @ np.swapaxes(Rb, 1, 2)

    def warped_stiffness_blocks(self, R: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Assembled warped stiffness K' = sum_e R_e K_e R_e^T (block data (nnzb, 3, 3) [N/m]) and the
        warped rest loads sum_e R_e K_e X_e (N, 3) [N], so that the elastic forces are
        f = -K' (x - c) + rest loads for any point c (K' annihilates translations). R: (E, 3, 3) or None.
        """
        if R is None and "_rest_blocks" in self.__dict__:
            return self._rest_blocks
        K, load = self.warped_stiffness_upper(R)
        K = self._upper.full(K)
        if R is None:  # warping off: the same every step
            K.flags.writeable = False
            self._rest_blocks = K, load
        return K, load

    def warped_stiffness_upper(self, R: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """As ``warped_stiffness_blocks``, with K' as its upper blocks (n_upper, 9) (see
        :class:`softbody.assembly.UpperAssembly`; ``system_blocks`` makes a system matrix of them).

        The material is isotropic, so R K_e(dN/dX) R^T = K_e(R dN/dX): the warped element stiffness
        is the rest formula with rotated gradients g = R dN/dX. Per quadrature point its 3x3 blocks
        are w detJ [lam g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I], linear in S_ab = w detJ g_a g_b^T;
        so only S is summed (over the pairs a <= b, into the upper blocks) and K' follows per block. Likewise
        K_e X_e = sum_q w detJ (3 lam + 2 mu) g_a (as sum_b X_b g_b^T = I), one sparse product of R.
        """
        if R is None and "_rest_upper" in self.__dict__:
            return self._rest_upper
        E = self._Gw.shape[0]
        R9 = _components(np.broadcast_to(np.eye(3), (E, 3, 3)) if R is None else R)
        K, load = _warped_upper(R9, self._Gw, self._rest_P, self._upper, self._rotate_grads, self._lame,
                                self._isotropic, self._elements_c)
        if self._bulk_part is not None:  # a split stiffness's bulk part (regions, B-bar), an element of its own
            K1, load1 = _warped_upper(R9, *self._bulk_part, self._elements_c)
            K = K + K1
            load = None if load is None or load1 is None else load + load1
        if self._fibre is not None:  # the fibres' stiffness M_e (x) n n^T and rest loads, n = R a (softbody.fibres)
            a, Mf, p = self._fibre
            n = a if R is None else np.einsum("eij,ej->ei", R, a)
            K = K + self.pattern.assemble(fibre_element_matrices(Mf, n))[self._upper.upper].reshape(-1, 9)
            if load is not None:  # (the compiled paths' loads are the isotropic parts')
                load = load + self.scatter_nodal(p[:, :, None] * n[:, None, :])
        result = K, self.rest_loads(R) if load is None else load
        if R is None:  # warping off: the same every step
            for a in result:
                a.flags.writeable = False
            self._rest_upper = result
        return result

    def rest_loads(self, R: np.ndarray | None) -> np.ndarray:
        """Warped rest loads sum_e R_e K_e X_e (N, 3) [N] for R (E, 3, 3) (None: K X, computed once)."""
        if R is None and "_rest_loads0" in self.__dict__:
            return self._rest_loads0
        E = self.mesh.n_elements
        R9 = _components(np.broadcast_to(np.eye(3), (E, 3, 3)) if R is None else R)
        loads = (self._rest_load @ R9.reshape(-1)).reshape(-1, 3)
        if R is None:
            loads.flags.writeable = False
            self._rest_loads0 = loads
        return loads

    def _matrix_free_data(self, part: int = 0) -> tuple[np.ndarray, np.ndarray, tuple]:
        """Of the stiffness's ``part`` (0: the body's, 1: a split body's bulk part): its weighted gradients
        node-major (E, k q, 3), its stress map (9q, 9q) and its Lame parameters, made at first use."""
        if "_mf" not in self.__dict__:
            self._mf = {}
        if part not in self._mf:
            Gw, lame = (self._Gw, self._lame) if part == 0 else (self._bulk_part.gradients, self._bulk_part.lame)
            E, q = Gw.shape[:2]
            G = np.ascontiguousarray(Gw.transpose(0, 2, 1, 3)).reshape(E, -1, 3)
            G.flags.writeable = False
            self._mf[part] = (G, stress_map(*lame, q), lame)
        return self._mf[part]

    def rotated_gradients(self, R: np.ndarray | None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """sqrt(w detJ) R_e dN_a/dX at every quadrature point, (E, k, 3q), entry (e, a, 3 q + j) [m^0.5]:
        what ``warped_product`` needs to apply K' = sum_e R_e K_e R_e^T. R: (E, 3, 3) or None (read-only then). A
        body whose stiffness is split (regions, volumetric='mean') gets a pair: its shear and bulk parts'."""
        parts = (0,) if self._bulk_part is None else (0, 1)
        out = []
        for part in parts:
            G, _, _ = self._matrix_free_data(part)
            E, kq, _ = G.shape
            k = self.mesh.elements.shape[1]
            out.append(G.reshape(E, k, 3 * (kq // k)) if R is None
                       else (G @ np.swapaxes(R, 1, 2)).reshape(E, k, 3 * (kq // k)))
        return out[0] if len(out) == 1 else tuple(out)

    def warped_product(self, g: np.ndarray | tuple, y: np.ndarray) -> np.ndarray:
        """K' y (N, 3) [N] for y (N, 3) [m], with g = ``rotated_gradients(R)``; K' is never formed. Per
        product this costs more than a sparse product with an assembled K', but it needs no assembly."""
        parts = g if isinstance(g, tuple) else (g,)
        if len(parts) != (1 if self._bulk_part is None else 2) or np.shape(y) != (self.n_nodes, 3):
            raise InvalidInputError(f"warped_product needs g from rotated_gradients and y of shape "
                                    f"{(self.n_nodes, 3)}, got {len(parts)} part(s) and {np.shape(y)}")
        out = np.zeros((self.n_nodes, 3))
        for part, gp in enumerate(parts):
            G, stress, lame = self._matrix_free_data(part)
            E, kq, _ = G.shape
            k = self.mesh.elements.shape[1]
            if np.shape(gp) != (E, k, 3 * (kq // k)):
                raise InvalidInputError(f"warped_product needs g of shape {(E, k, 3 * (kq // k))} (rotated_gradients), "
                                        f"got {np.shape(gp)}")
            if kernels.ENABLED:  # the same sums element by element, the stress in closed form (softbody.kernels)
                one = np.empty((self.n_nodes, 3))
                kernels.warped_product(np.ascontiguousarray(gp, dtype=float), self._elements_c, *lame,
                                       np.ascontiguousarray(y, dtype=float), one)
                out += one
            else:
                out += warped_product(gp, self.mesh.elements, stress, self._scatter, y)
        return out

    def warped_diagonal(self, g: np.ndarray | tuple) -> np.ndarray:
        """The diagonal blocks (N, 3, 3) of K' [N/m] with g = ``rotated_gradients(R)``, K' never formed (what a solve
        that applies K' by ``warped_product`` needs of its diagonal: scalings, Delassus estimates)."""
        parts = g if isinstance(g, tuple) else (g,)
        if len(parts) != (1 if self._bulk_part is None else 2):
            raise InvalidInputError(f"warped_diagonal needs g from rotated_gradients, got {len(parts)} part(s)")
        out = np.zeros((self.n_nodes, 3, 3))
        for part, gp in enumerate(parts):
            _, _, lame = self._matrix_free_data(part)
            if kernels.ENABLED:  # the same sums element by element (softbody.kernels)
                one = np.empty((self.n_nodes, 3, 3))
                kernels.warped_diagonal(np.ascontiguousarray(gp, dtype=float), self._elements_c, *lame, one)
                out += one
            else:
                out += warped_diagonal(gp, *lame, self._scatter)
        return out

    @property
    def prefers_matrix_free(self) -> bool:
        """Whether a step that only applies K' (IterativeSettings.operator "auto") should skip its
        assembly and use ``warped_product``: with warping on (else K' is assembled once and kept), for
        elements whose node pairs k (k + 1) / 2 outnumber their gradient entries q k (tet10: 55 pairs
        against 40), where assembly dominates. One-point elements (tet4) have their own cheap assembly,
        and hex8 (36 pairs, 64 gradients) is faster assembled."""
        E, q, k, _ = self._Gw.shape
        return self.warping and self._fibre is None and q > 1 and k * (k + 1) // 2 > q * k

    @property
    def diagonal_upper(self) -> np.ndarray:
        """(N,) position of each node's diagonal block in the upper block data."""
        return self._upper.diag

    @property
    def mass_scale(self) -> float:
        """Largest diagonal entry of the mass matrix [kg]."""
        if "_mass_scale" not in self.__dict__:
            self._mass_scale = float(self.M_data[self.pattern.diag].max())
        return self._mass_scale

    def stiffness_blocks(self, K_upper: np.ndarray) -> np.ndarray:
        """Block data (nnzb, 3, 3) of the symmetric matrix with upper blocks K_upper (n_upper, 9)."""
        return self._upper.full(K_upper)

    def system_blocks(self, K_upper: np.ndarray, c_m: float, c_k: float) -> np.ndarray:
        """Block data (nnzb, 3, 3) of c_m M + c_k K for K given by its upper blocks (n_upper, 9)."""
        if kernels.ENABLED:  # the lines below in one pass, block by block (softbody.kernels)
            out = np.empty((self.pattern.nnzb, 3, 3))
            kernels.system_blocks(np.ascontiguousarray(K_upper, dtype=float), self._mass_upper, c_m, c_k,
                                  *self._upper.full_sources(), out)
            return out
        A = c_k * K_upper
        A[:, [0, 4, 8]] += (c_m * self._mass_upper)[:, None]
        return self._upper.full(A)

    def elastic_energy(self, x: np.ndarray | None = None) -> float:
        """Strain energy [J] at positions x (default: current): the warped 1/2 sum_e u_e^T K_e u_e with u_e the
        unrotated displacement, or the hyperelastic model's."""
        x = self.positions if x is None else x
        if self._hyper is not None:
            return self._hyper.energy(np.asarray(x, dtype=float)[self.mesh.elements])
        u = self.local_displacements(x, self.rotations(x))
        return 0.5 * float(np.sum(u * (self.Ke @ u[:, :, None])[:, :, 0]))

    def gravitational_energy(self, gravity, x: np.ndarray | None = None) -> float:
        """Potential energy [J] in the uniform field ``gravity`` (3,) [m/s^2] at positions x (default:
        current): -sum_i m_i (x_i . g) with the consistent nodal masses, zero at the origin."""
        x = self.positions if x is None else x
        return -float(self.node_mass @ (x @ np.asarray(gravity, dtype=float)))

    def kinetic_energy(self, v: np.ndarray | None = None) -> float:
        v = self.velocities if v is None else v
        return 0.5 * float(np.sum(v * self.mass_product(v)))

    # ------------------------------------------------------------------ output
    def _centre_gradients(self, x: np.ndarray) -> np.ndarray:
        """The deformation gradient F (E, 3, 3) at each element centre."""
        xe = np.asarray(x, dtype=float)[self.mesh.elements]
        return np.einsum("eka,ekb->eab", xe - xe.mean(axis=1, keepdims=True), self._Gc)

    def strain(self, x: np.ndarray | None = None) -> np.ndarray:
        """Strain at each element centre, Voigt (E, 6) (engineering shear): the small strain in the element's
        rotated frame (linear models), the Green-Lagrange strain (F^T F - I) / 2 (hyperelastic models)."""
        x = self.positions if x is None else x
        if self._hyper is not None:
            F = self._centre_gradients(x)
            return _voigt(0.5 * (np.swapaxes(F, 1, 2) @ F - np.eye(3)), shear=2.0)
        u = self.local_displacements(x, self.rotations(x))
        H = np.einsum("eka,ekb->eab", u.reshape(len(u), -1, 3), self._Gc)  # displacement gradients (E, 3, 3)
        eps = _voigt(0.5 * (H + np.swapaxes(H, 1, 2)), shear=2.0)
        if self.volumetric == "mean":  # B-bar: the volume change is the element's mean, not the centre's
            eps[:, :3] += ((np.einsum("ej,ej->e", self._mean_divergence, u) - eps[:, :3].sum(axis=1)) / 3.0)[:, None]
        return eps

    def stress(self, x: np.ndarray | None = None) -> np.ndarray:
        """Cauchy stress at each element centre, Voigt (E, 6) [Pa]: of the small strain in the element's rotated
        frame (linear models), or the hyperelastic law's P F^T / det F (in world axes)."""
        if self._hyper is not None:
            F = self._centre_gradients(self.positions if x is None else x)
            lam, mu = self.material.lame
            return _voigt(self._hyper.cauchy_stress(F, lam, mu))
        eps = self.strain(x)
        sigma = np.einsum("eij,ej->ei", self.D, eps) if self.D.ndim == 3 else eps @ self.D.T  # (D by element: Regions)
        if self._fibre is not None:  # E_f eps_aa a a^T
            a = self._fibre[0]
            aa = np.stack([a[:, 0] ** 2, a[:, 1] ** 2, a[:, 2] ** 2, a[:, 0] * a[:, 1], a[:, 1] * a[:, 2],
                           a[:, 2] * a[:, 0]], axis=1)
            eps_aa = np.einsum("ei,ei->e", eps, aa)  # (the engineering shears count once: a . eps a)
            sigma = sigma + (self.fibres.per_element(len(a))[1] * eps_aa)[:, None] * aa
        return sigma

    def von_mises(self, x: np.ndarray | None = None) -> np.ndarray:
        """Von Mises stress at each element centre (E,) [Pa]."""
        return von_mises_stress(self.stress(x))

    # ------------------------------------------------------------------ rest-state matrices
    def stiffness_matrix(self) -> sp.csr_matrix:
        """Rest stiffness K (3N x 3N, interleaved DOFs) as CSR."""
        return self.pattern.to_csr(self.pattern.assemble(self.Ke))

    def mass_matrix(self) -> sp.csr_matrix:
        """Mass matrix M (3N x 3N) as CSR (consistent or lumped)."""
        return self.pattern.to_csr(self.M_blocks)
