"""Writers for reconstruction results: markers CSV, PLY (points/normals or mesh), STL, NPZ, PNG preview.

All coordinates are written as given (sensor frame, mm). Every writer is atomic
(:mod:`pipeline.io.atomic`): a result file is complete or absent, never half written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.atomic import atomic_open, savefig_atomic
from pipeline.types import DataError, HeightMap, MarkerCloud

__all__ = ["write_markers_csv", "read_markers_csv", "write_ply", "read_ply_vertices", "heightmap_mesh",
           "write_stl", "write_heightmap_npz", "write_preview_png"]


def write_markers_csv(path: str | Path, cloud: MarkerCloud) -> None:
    """CSV with header ``id,x_mm,y_mm,z_mm``, one marker per row, 6 decimals (1 nm)."""
    with atomic_open(path, "w") as fh:
        fh.write("id,x_mm,y_mm,z_mm\n")
        for i, (x, y, z) in zip(cloud.ids, cloud.xyz_mm):
            fh.write(f"{int(i)},{x:.6f},{y:.6f},{z:.6f}\n")


def read_markers_csv(path: str | Path) -> MarkerCloud:
    """Inverse of :func:`write_markers_csv`; a malformed file is a :class:`DataError` naming it."""
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError) as exc:   # UnicodeDecodeError is a ValueError
        raise DataError(f"markers file {path}: not a markers CSV ({type(exc).__name__}: {str(exc)[:100]})") from None
    if data.size and data.shape[1] != 4:
        raise DataError(f"markers file {path}: expected 4 columns id,x_mm,y_mm,z_mm, got {data.shape[1]}")
    if data.size == 0:
        return MarkerCloud(np.empty(0, np.int64), np.empty((0, 3)))
    return MarkerCloud(data[:, 0].astype(np.int64), data[:, 1:4])


def write_ply(path: str | Path, points: np.ndarray, *, normals: np.ndarray | None = None,
              faces: np.ndarray | None = None, binary: bool = False,
              comment: str = "StereoTacTip, sensor frame, mm") -> None:
    """PLY with vertices (N, 3), optional per-vertex normals (N, 3) and triangle faces (F, 3).

    ``binary`` writes little-endian binary (float64 vertices, int32 indices); otherwise ASCII. ``comment``
    names the frame and units of the coordinates (one header line).
    """
    if "\n" in comment or "\r" in comment:
        raise ValueError("write_ply: the comment must be one line")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    tri = None if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if nrm is not None and len(nrm) != len(pts):
        raise ValueError(f"write_ply: {len(nrm)} normals for {len(pts)} points")
    fmt = "binary_little_endian" if binary else "ascii"
    typ = "double" if binary else "float"
    head = ["ply", f"format {fmt} 1.0", f"comment {comment}", f"element vertex {len(pts)}",
            f"property {typ} x", f"property {typ} y", f"property {typ} z"]
    if nrm is not None:
        head += [f"property {typ} nx", f"property {typ} ny", f"property {typ} nz"]
    if tri is not None:
        head += [f"element face {len(tri)}", "property list uchar int vertex_indices"]
    head.append("end_header")
    vert = pts if nrm is None else np.hstack([pts, nrm])
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii"))
        if binary:
            fh.write(vert.astype("<f8").tobytes())
            if tri is not None:
                rec = np.zeros(len(tri), dtype=[("n", "u1"), ("v", "<i4", (3,))])
                rec["n"] = 3
                rec["v"] = tri
                fh.write(rec.tobytes())
        else:
            np.savetxt(fh, vert, fmt="%.6f")
            if tri is not None:
                np.savetxt(fh, np.column_stack([np.full(len(tri), 3), tri]), fmt="%d")


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """Vertices (N, 3) of a PLY written by :func:`write_ply` (ASCII or binary); a truncated or foreign
    file is a :class:`DataError` naming it."""
    try:
        return _read_ply_vertices(Path(path).read_bytes())
    except (OSError, ValueError, IndexError, StopIteration) as exc:
        raise DataError(f"PLY file {path}: unreadable or not written by this project ({type(exc).__name__})") from None


def _read_ply_vertices(raw: bytes) -> np.ndarray:
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    head = raw[:end].decode("ascii").splitlines()
    iv = next(k for k, h in enumerate(head) if h.startswith("element vertex"))
    n = int(head[iv].split()[2])
    nprop = 0
    for h in head[iv + 1:]:
        if not h.startswith("property"):
            break
        nprop += 1
    if "format ascii 1.0" in head:
        rows = raw[end:].decode("ascii").split("\n")[:n]
        pts = np.array([[float(v) for v in r.split()[:3]] for r in rows if r.strip()]).reshape(-1, 3)
        if len(pts) != n:
            raise ValueError(f"{len(pts)} of {n} vertices")
        return pts
    return np.frombuffer(raw[end:end + 8 * nprop * n], dtype="<f8").reshape(n, nprop)[:, :3].copy()


def heightmap_mesh(hm: HeightMap) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of the valid (non-NaN) cells of a height map: vertices (V, 3) mm, faces (F, 3).

    Each grid square whose four corners are valid becomes two triangles (counter-clockwise seen from +z,
    so face normals point out of the skin).
    """
    H, W = hm.z_mm.shape
    gx, gy = np.meshgrid(hm.x_mm, hm.y_mm)
    valid = np.isfinite(hm.z_mm)
    index = -np.ones((H, W), dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    verts = np.column_stack([gx[valid], gy[valid], hm.z_mm[valid]])
    if H < 2 or W < 2:
        return verts, np.empty((0, 3), dtype=np.int64)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    ok = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.column_stack([a[ok], b[ok], d[ok]]), np.column_stack([a[ok], d[ok], c[ok]])])
    return verts, faces


def write_stl(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary STL via trimesh."""
    import trimesh

    data = trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64),
                           process=False).export(file_type="stl")
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def write_heightmap_npz(path: str | Path, hm: HeightMap) -> None:
    """``x_mm``, ``y_mm``, ``z_mm`` arrays (``HeightMap.load_npz`` reads it back)."""
    hm.save_npz(path)


def write_preview_png(path: str | Path, hm: HeightMap | None, cloud: MarkerCloud | None = None, *,
                      title: str = "") -> None:
    """Preview figure: height map (colour bar in mm) with the markers' x-y positions on top, and a
    side view of the marker cloud (x vs z)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    ax = axes[0]
    if hm is not None and np.isfinite(hm.z_mm).any():
        im = ax.imshow(hm.z_mm, origin="lower", extent=(hm.x_mm[0], hm.x_mm[-1], hm.y_mm[0], hm.y_mm[-1]),
                       cmap="viridis")
        fig.colorbar(im, ax=ax, label="skin height z (mm)")
    if cloud is not None and len(cloud):
        ax.plot(cloud.xyz_mm[:, 0], cloud.xyz_mm[:, 1], ".", color="w", ms=3, mec="k", mew=0.3)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    ax.set_title("skin height map")
    ax = axes[1]
    if cloud is not None and len(cloud):
        sc = ax.scatter(cloud.xyz_mm[:, 0], cloud.xyz_mm[:, 2], c=cloud.xyz_mm[:, 1], s=8, cmap="coolwarm")
        fig.colorbar(sc, ax=ax, label="y (mm)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("markers (side view)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        savefig_atomic(fig, path, dpi=100)
    finally:
        plt.close(fig)
