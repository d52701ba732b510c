"""Soft bodies from triangle surfaces: :func:`tetrahedralize` fills a closed surface with tets through gmsh.

Why gmsh: its Python API (``pip install gmsh``, a self-contained wheel, the ``mesh`` extra) re-meshes a
triangulated surface to a target edge length (``classifySurfaces`` + ``createGeometry``: the input triangles
become the geometry, so the new surface nodes lie on them) and fills it with Delaunay tets. It has been
developed by its original authors since 1997, is deterministic on one thread, and reports defects of the
input (intersecting facets) instead of meshing past them. fTetWild (pytetwild) meshes dirty surfaces
robustly, but its wheel pulls in pyvista and VTK, and it changes the shape it repairs; here a surface must
be clean: small holes (one missing triangle or quad) are filled with a warning, anything else is an error
naming the defect.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .errors import InvalidInputError, MeshError
from .mesh import Mesh

SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")


def _as_trimesh(surface):
    """A trimesh.Trimesh from a Trimesh, a (vertices (V, 3), faces (F, 3)) pair, or a file path."""
    import trimesh

    if isinstance(surface, (str, Path)):
        path = Path(surface)
        if not path.exists():
            raise InvalidInputError(f"surface file {str(path)!r} does not exist")
        if path.suffix.lower() not in SURFACE_SUFFIXES:
            raise InvalidInputError(f"surface file {str(path)!r}: expected one of {', '.join(SURFACE_SUFFIXES)}")
        try:
            loaded = trimesh.load(str(path), force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types
            raise MeshError(f"trimesh could not read {str(path)!r}: {exc}") from exc
        vertices, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
        name = repr(str(path))
    elif isinstance(surface, trimesh.Trimesh):
        vertices, faces, name = np.asarray(surface.vertices), np.asarray(surface.faces), "the surface"
    elif isinstance(surface, (tuple, list)) and len(surface) == 2:
        vertices, faces, name = surface[0], surface[1], "the surface"
    else:
        raise InvalidInputError("surface must be a trimesh.Trimesh, a (vertices (V, 3), faces (F, 3)) pair or the "
                                f"path of a {'/'.join(s[1:].upper() for s in SURFACE_SUFFIXES)} file, "
                                f"got {type(surface).__name__}")
    try:
        vertices = np.array(vertices, dtype=float)
        faces = np.array(faces)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"surface vertices and faces must be numeric arrays: {exc}") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise InvalidInputError(f"surface vertices must be a finite (V, 3) array [m], got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4 or not np.issubdtype(faces.dtype, np.integer):
        raise InvalidInputError(f"surface faces must be an integer (F, 3) array of at least 4 triangles, got "
                                f"shape {faces.shape}, dtype {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidInputError(f"surface faces reference vertices outside [0, {len(vertices) - 1}]")
    # process=True merges coincident vertices (STL, and OBJ seams of texture coordinates) and drops
    # degenerate and duplicate faces
    mesh = trimesh.Trimesh(vertices, faces, process=True, validate=True)
    return mesh, name


def _check_closed(mesh, name: str, repair: bool):
    """The watertight, consistently wound, outward surface of ``mesh``: small holes are filled (``repair``,
    with a warning); open or non-manifold surfaces and several shells raise MeshError."""
    import trimesh

    if not mesh.is_watertight and repair:
        before = len(mesh.faces)
        trimesh.repair.fill_holes(mesh)
        if mesh.is_watertight:
            warnings.warn(f"{name} had holes: filled with {len(mesh.faces) - before} triangles", stacklevel=3)
    if not mesh.is_watertight:
        edges = mesh.edges_sorted
        _, counts = np.unique(edges, axis=0, return_counts=True)
        open_edges, shared = int((counts == 1).sum()), int((counts > 2).sum())
        raise MeshError(f"{name} is not closed: {open_edges} edges belong to one triangle only (a hole)"
                        + (f" and {shared} to more than two (non-manifold)" if shared else "")
                        + "; a volume needs a watertight surface (fill the holes, e.g. in Blender or with "
                          "trimesh.repair.fill_holes for small ones; pass repair=True for those)")
    shells = mesh.split(only_watertight=False)
    if len(shells) > 1:
        raise MeshError(f"{name} has {len(shells)} separate shells; tetrahedralize them one by one "
                        "(trimesh's mesh.split()) and add each as a body, or join them into one surface")
    trimesh.repair.fix_normals(mesh)  # consistent winding, outward
    if mesh.volume <= 0:
        raise MeshError(f"{name} encloses no volume ({mesh.volume:.3g} m^3)")
    return mesh


def _gmsh_tets(vertices: np.ndarray, faces: np.ndarray, size: float, remesh: bool, name: str, optimize: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) and tet4 elements (E, 4) of the volume inside the closed surface, by gmsh."""
    try:
        import gmsh
    except ImportError as exc:
        raise InvalidInputError('tetrahedralize needs gmsh: pip install "softbody[mesh]" (or pip install gmsh)') from exc
    gmsh.initialize(interruptible=False)  # no SIGINT handler of its own: Ctrl-C stays Python's
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)  # deterministic
        gmsh.logger.start()
        gmsh.model.add("surface")
        tag = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, tag, np.arange(1, len(vertices) + 1), vertices.ravel())
        gmsh.model.mesh.addElementsByType(tag, 2, [], (faces + 1).ravel())
        if remesh:  # the triangles become a reparametrisable geometry, re-meshed at ``size``
            gmsh.model.mesh.classifySurfaces(np.pi, True, True, np.pi)
            gmsh.model.mesh.createGeometry()
        surfaces = [t for _, t in gmsh.model.getEntities(2)]
        gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop(surfaces)])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeMin", size / 4)
        gmsh.option.setNumber("Mesh.Optimize", int(optimize))
        gmsh.option.setNumber("Mesh.OptimizeNetgen", int(optimize))  # fewer slivers
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:
            log = [m for m in gmsh.logger.get() if "rror" in m]
            text = "; ".join(log[-3:]) or str(exc)
            hint = (" The surface intersects itself: repair it (e.g. MeshLab's 'remove self intersections', "
                    "or fTetWild for dirty surfaces)." if "intersect" in text.lower() else "")
            raise MeshError(f"gmsh could not fill {name} with tets: {text}.{hint}") from None
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etags, enodes = gmsh.model.mesh.getElementsByType(4)
    finally:
        gmsh.logger.stop()
        gmsh.finalize()
    if len(etags) == 0:
        raise MeshError(f"gmsh made no tets inside {name} (is it closed and is size small enough?)")
    index = np.full(int(tags.max()) + 1, -1)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    elements = index[enodes.astype(np.int64).reshape(-1, 4)]
    nodes = coords.reshape(-1, 3)
    used = np.unique(elements)
    renumber = np.full(len(nodes), -1)
    renumber[used] = np.arange(len(used))
    return nodes[used], renumber[elements]


def _closest_on_surface(surface, points: np.ndarray, candidates: int = 16) -> np.ndarray:
    """The closest points (M, 3) [m] of the triangle surface to ``points`` (M, 3), among the ``candidates``
    triangles whose centroids are nearest (vectorised; exact for points near the surface)."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    k = min(candidates, len(surface.faces))
    _, near = cKDTree(surface.triangles_center).query(points, k=k)
    near = near.reshape(len(points), k)
    tris = surface.triangles[near.ravel()]
    cand = closest_point(tris, np.repeat(points, k, axis=0)).reshape(len(points), k, 3)
    best = np.argmin(np.linalg.norm(cand - points[:, None], axis=2), axis=1)
    return cand[np.arange(len(points)), best]


def _curved_tet10(mesh: Mesh, surface, name: str) -> Mesh:
    """tet10 from tet4 with the midside nodes of surface edges projected onto ``surface``; where that would
    invert an element, its projections are pulled back towards the chords (halved up to 8 times, then straight)."""
    from .elements import element_type, jacobians
    from .meshing import to_tet10

    quad = to_tet10(mesh)
    surf = quad.surface_nodes()
    mid = surf[surf >= mesh.n_nodes]
    target = quad.nodes.copy()
    target[mid] = _closest_on_surface(surface, quad.nodes[mid])
    offset = target - quad.nodes  # zero off the surface
    frac = np.ones(quad.n_nodes)
    et = element_type("tet10")
    for _ in range(9):
        nodes = quad.nodes + frac[:, None] * offset
        det = np.linalg.det(jacobians(et, nodes[quad.elements], et.check_points))
        scale = np.abs(det).max()
        bad = np.flatnonzero((det <= 1e-12 * scale).any(axis=1))
        if bad.size == 0:
            break
        frac[quad.elements[bad, 4:].ravel()] *= 0.5
    else:
        frac[quad.elements[bad, 4:].ravel()] = 0.0
        nodes = quad.nodes + frac[:, None] * offset
    short = np.flatnonzero(frac[mid] < 1)
    if short.size:
        warnings.warn(f"tetrahedralize {name}: {short.size} of {len(mid)} surface midside nodes kept between their "
                      "edge's chord and the surface (projected all the way they would invert an element)", stacklevel=3)
    return Mesh(nodes, quad.elements, "tet10")


def tetrahedralize(surface, size: float, kind: str = "tet4", remesh: bool = True, repair: bool = True) -> Mesh:
    """A volume mesh filling a closed triangle surface, through gmsh (``pip install "softbody[mesh]"``).

    surface: a trimesh.Trimesh, a (vertices (V, 3) [m], faces (F, 3)) pair, or the path of an STL, OBJ, PLY
    (or OFF, glTF) file, in metres; coincident vertices are merged (STL files, OBJ texture seams), the winding
    made consistent and outward. size: the target edge length [m] (gmsh's largest size; it may go down to
    size/4 where the surface needs it). kind: "tet4" or "tet10": tet10 adds a node on every edge, and those on
    surface edges are projected onto the input surface (closest point), so the faces curve with it (pulled
    back towards the chord only where the projection would invert an element, with a warning). remesh: re-mesh
    the surface at ``size`` (True) or keep the input triangles as the boundary (False: their edge lengths
    win). repair: fill small holes (one missing triangle or quad) with a warning.

    Raises MeshError naming the defect for a surface that is not closed (holes, non-manifold edges), that has
    several shells, or that intersects itself (gmsh's report), and InvalidInputError for bad arguments.
    """
    if kind not in ("tet4", "tet10"):
        raise InvalidInputError(f"tetrahedralize makes tets: kind must be 'tet4' or 'tet10', got {kind!r}")
    if not (isinstance(size, (int, float, np.number)) and not isinstance(size, bool) and np.isfinite(size)
            and size > 0):
        raise InvalidInputError(f"size must be a target edge length > 0 [m], got {size!r}")
    mesh, name = _as_trimesh(surface)
    mesh = _check_closed(mesh, name, repair)
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    if size > extent:
        raise InvalidInputError(f"size {size:g} m is larger than {name} ({extent:.3g} m across); "
                                f"take at most a third of it, e.g. {extent / 3:.3g}")
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    if remesh:  # the input triangles as they are, coarse inside: gmsh refuses a surface that intersects itself
        _gmsh_tets(vertices, faces, extent, False, name, optimize=False)  # (re-meshing it first could hide the defect)
    nodes, tets = _gmsh_tets(vertices, faces, float(size), remesh, name)
    from .meshing import _orient_tets

    tet4 = Mesh(nodes, _orient_tets(nodes, tets), "tet4")
    return _curved_tet10(tet4, mesh, name) if kind == "tet10" else tet4
