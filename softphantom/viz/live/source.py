"""Estimate sources for the live view: the interface, the surface geometry, and two sources
(a synthetic push for demos/tests, a replay of a recording or estimate CSV).

The interface (:class:`EstimateSource`) is what the estimator must offer to be shown live:

- ``geometry`` — a :class:`LiveGeometry` (the PhantomModel's outer surface, targets, p_ext, arms);
- ``layout`` — the phantom's :class:`~softphantom.records.channels.ChannelLayout` (the estimates'
  volume and pressure keys, the page's cavity plot, the recording's schemas and metadata);
- iterating it yields :class:`~softphantom.estimation.Estimate` objects, in time order, as they are
  computed (a real-time source paces itself; the live view never sleeps between them);
- ``node_positions()`` — on demand, the deformed positions ``(N, 3)`` m of the model's nodes for the
  last estimate yielded (``None`` if unknown); the live view calls it at its view rate only;
- optional: ``last_measurement()`` (the ``Measurement`` behind the last estimate, recorded on
  ``/sensors``), ``poll_tracker()`` (tracker messages since the last call, recorded on ``/tracker``),
  ``close()``.

:func:`softphantom.sources.open_source` opens them by ``--source`` (``synthetic``; ``replay:`` of a
session recording or an estimate file); :class:`EstimatorSource` wraps a sensor source (board,
virtual phantom, sensing recording) and the estimator.
"""

from __future__ import annotations

import base64
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Protocol, runtime_checkable

import numpy as np

from softphantom.errors import FileFormatError, UserError
from softphantom.records.estimate import Estimate, message_to_estimate
from softphantom.records.channels import BIP_LAYOUT, ChannelLayout, ChannelNames, read_layout


TRI6_SPLIT = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
"""A 6-node triangle (corners, then the mid-edge nodes of (0,1), (1,2), (2,0)) as 4 flat ones of
the same orientation, so the drawn surface bends through the mid-edge nodes."""


def split_tri6(faces6: np.ndarray) -> np.ndarray:
    """(S, 6) quadratic triangles → (4S, 3) flat ones through all six nodes.

    >>> split_tri6(np.array([[0, 1, 2, 3, 4, 5]])).tolist()
    [[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]]
    """
    return np.asarray(faces6, np.int64)[:, TRI6_SPLIT].reshape(-1, 3)


@dataclass(frozen=True)
class LiveGeometry(ChannelNames):
    """The surfaces the live view draws (SI units).

    ``nodes`` (n, 3) m rest positions of the drawn nodes; ``faces`` (S, 3) indices into ``nodes``,
    the outer surface (outward normals); ``cavities`` name → (K, 3) indices into ``nodes``, each
    cavity's wall; ``node_index`` (n,) the model node id of each drawn node, to pick them out of
    ``node_positions()``; ``targets`` name → (3,) m at rest; ``p_ext`` (3,) m where the force
    acts; ``contact_radius_m`` the estimator's contact patch radius (None: not an estimator's
    view), recorded with the geometry so a recording says which contact model it used;
    ``layout`` the phantom's :class:`~softphantom.records.channels.ChannelLayout` (its design's; the
    JSON's ``channels``, and its volume channels as ``arms`` for the page).

    >>> g = ellipsoid_geometry(subdivisions=1)
    >>> g.nodes.shape, g.faces.shape, sorted(g.targets), sorted(g.cavities)
    ((252, 3), (80, 3), ['apex', 'base', 'lesion'], ['back_xneg', 'back_xpos', 'front_zneg', 'front_zpos', 'urethra'])
    """

    nodes: np.ndarray
    faces: np.ndarray
    node_index: np.ndarray
    targets: dict[str, np.ndarray] = field(default_factory=dict)
    p_ext: np.ndarray = field(default_factory=lambda: np.zeros(3))
    contact_radius_m: float | None = None
    cavities: dict[str, np.ndarray] = field(default_factory=dict)
    layout: ChannelLayout = BIP_LAYOUT

    @classmethod
    def from_model(cls, model: Any, p_ext: str = "on-centre", contact_radius_m: float | None = None) -> "LiveGeometry":
        """The outer surface and the cavities of a ``PhantomModel`` (docs/architecture.md), reindexed
        to the nodes they use, its ``targets``, the ``p_ext`` point named ``p_ext`` and its
        ``layout`` (the BIP's for a model-like object without one). A quadratic
        model's 6-node triangles (``outer_faces6``, ``cavities6``) are drawn as 4 flat ones each
        (:func:`split_tri6`), through their mid-edge nodes."""
        faces6 = np.asarray(getattr(model, "outer_faces6", np.zeros((0, 6))), dtype=np.int64).reshape(-1, 6)
        quadratic = len(faces6) > 0
        faces = split_tri6(faces6) if quadratic else np.asarray(model.outer_faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise UserError("the model has no outer surface triangles (outer_faces)")
        walls = getattr(model, "cavities6", {}) if quadratic else getattr(model, "cavities", {})
        cavities = {k: split_tri6(v) if quadratic else np.asarray(v, np.int64).reshape(-1, 3)
                    for k, v in (walls or {}).items()}
        sizes = np.cumsum([len(faces), *(len(v) for v in cavities.values())])[:-1]
        used, inv = np.unique(np.concatenate([faces.ravel(), *(v.ravel() for v in cavities.values())]),
                              return_inverse=True)
        parts = np.split(inv.reshape(-1, 3).astype(np.int64), sizes)
        points = dict(getattr(model, "p_ext", {}) or {})
        if p_ext not in points:
            raise UserError(f"the model has no interaction point {p_ext!r}; it has: {', '.join(points) or 'none'}")
        return cls(
            nodes=np.asarray(model.nodes, float)[used],
            faces=parts[0],
            node_index=used.astype(np.int64),
            targets={k: np.asarray(v, float) for k, v in (getattr(model, "targets", {}) or {}).items()},
            p_ext=np.asarray(points[p_ext], float),
            contact_radius_m=None if contact_radius_m is None else float(contact_radius_m),
            cavities=dict(zip(cavities, parts[1:])),
            layout=getattr(model, "layout", BIP_LAYOUT),
        )

    def to_json(self) -> dict[str, Any]:
        """JSON for the page and the ``/live/geometry`` channel (millimetres)."""
        outer = np.unique(self.faces)  # the force acts on the outer surface, not on a cavity wall
        pe = int(outer[np.argmin(np.linalg.norm(self.nodes[outer] - self.p_ext, axis=1))])
        out = {
            "nodes_mm": np.round(self.nodes * 1e3, 4).tolist(),
            "faces": self.faces.tolist(),
            "cavities": {k: v.tolist() for k, v in self.cavities.items()},
            "targets_mm": {k: np.round(v * 1e3, 4).tolist() for k, v in self.targets.items()},
            "p_ext_mm": np.round(self.p_ext * 1e3, 4).tolist(),
            "p_ext_node": pe,
            "arms": list(self.arm_names),
            **self.layout.to_meta(),
        }
        if self.contact_radius_m is not None:
            out["contact_radius_mm"] = round(self.contact_radius_m * 1e3, 6)
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "LiveGeometry":
        """Inverse of :meth:`to_json` (``node_index`` = 0..n-1)."""
        try:
            nodes = np.asarray(d["nodes_mm"], float).reshape(-1, 3) * 1e-3
            faces = np.asarray(d["faces"], np.int64).reshape(-1, 3)
            targets = {k: np.asarray(v, float) * 1e-3 for k, v in d.get("targets_mm", {}).items()}
            p_ext = np.asarray(d.get("p_ext_mm", [0, 0, 0]), float) * 1e-3
            radius = d.get("contact_radius_mm")
            radius = None if radius is None else float(radius) * 1e-3
            cavities = {k: np.asarray(v, np.int64).reshape(-1, 3) for k, v in d.get("cavities", {}).items()}
            layout = read_layout(d, "geometry message", sensing=d.get("arms"))
        except (KeyError, ValueError, TypeError) as exc:
            raise FileFormatError(f"geometry message is malformed: {exc}") from None
        return cls(nodes, faces, np.arange(len(nodes), dtype=np.int64), targets, p_ext, radius, cavities, layout)


def encode_positions_mm(positions_m: np.ndarray) -> str:
    """Surface positions (n, 3) m → base64 of little-endian float32 millimetres (the wire form).

    >>> decode_positions_mm(encode_positions_mm(np.array([[0.001, 0.0, -0.002]])))
    array([[ 0.001,  0.   , -0.002]])
    """
    return base64.b64encode((np.asarray(positions_m) * 1e3).astype("<f4").tobytes()).decode()


def decode_positions_mm(b64: str) -> np.ndarray:
    """Inverse of :func:`encode_positions_mm` (metres, float64, rounded to 0.1 µm)."""
    return np.round(np.frombuffer(base64.b64decode(b64), "<f4").reshape(-1, 3).astype(float) * 1e-3, 7)


@runtime_checkable
class EstimateSource(Protocol):
    """What the live view needs from an estimator (see the module docstring)."""

    geometry: LiveGeometry

    def __iter__(self) -> Iterator[Estimate]: ...

    def node_positions(self) -> np.ndarray | None: ...


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        nf = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    return np.array(verts), np.array(faces, dtype=np.int64)


_STAND_IN_CAVITIES = {  # centre (m), semi-axes (m): where the design's arms and urethra run, roughly
    "front_zpos": ((0.0, -0.010, 0.013), (0.005, 0.007, 0.004)),
    "front_zneg": ((0.0, -0.010, -0.013), (0.005, 0.007, 0.004)),
    "back_xpos": ((0.015, 0.010, 0.0), (0.004, 0.007, 0.005)),
    "back_xneg": ((-0.015, 0.010, 0.0), (0.004, 0.007, 0.005)),
    "urethra": ((0.0, 0.0, 0.004), (0.0025, 0.020, 0.0025)),
}


def ellipsoid_geometry(semi_axes_m: tuple[float, float, float] = (0.032, 0.025, 0.030),
                       subdivisions: int = 3) -> LiveGeometry:
    """A stand-in bulb surface (the paper's ellipsoid, 100 mL) with small ellipsoidal stand-in
    cavities for the synthetic source."""
    unit, faces = _icosphere(subdivisions)
    small, small_faces = _icosphere(1)
    nodes, cavities = [unit * np.asarray(semi_axes_m)], {}
    for name, (centre, axes) in _STAND_IN_CAVITIES.items():
        cavities[name] = small_faces + sum(len(n) for n in nodes)
        nodes.append(small * np.asarray(axes) + np.asarray(centre))
    nodes = np.vstack(nodes)
    targets = {"apex": np.array([0.0, -0.015, 0.0]), "base": np.array([0.0, 0.015, 0.0]),
               "lesion": np.array([0.008, 0.0, -0.006])}
    return LiveGeometry(nodes, faces, np.arange(len(nodes), dtype=np.int64), targets,
                        np.array([0.0, -semi_axes_m[1], 0.0]), cavities=cavities)


def _rot(ypr: np.ndarray) -> np.ndarray:
    """R = Rz(yaw)·Rx(pitch)·Ry(roll) (the project's convention)."""
    (cy, sy), (cp, sp), (cr, sr) = [(math.cos(a), math.sin(a)) for a in ypr]
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
    return rz @ rx @ ry


class SyntheticSource:
    """A smooth, repeating push at p_ext on an ellipsoid: a **kinematic stand-in**, not physics.

    Force ``F(t) = peak·½(1−cos 2πt/period)`` mostly along +y (the needle direction) with small x/z
    parts; the bulb translates by F/k, rotates a few degrees and dents around p_ext; cavity volumes
    are a fixed linear map of (F, p_urethra) plus noise. Yields ``duration_s·rate_Hz`` estimates
    (forever if ``duration_s`` is None), paced in real time when ``realtime`` (late ticks are
    skipped and counted in ``Estimate.skipped``, as the estimator does).

    >>> s = SyntheticSource(rate_Hz=100, duration_s=0.5, realtime=False, subdivisions=1)
    >>> ests = list(s)
    >>> len(ests), round(float(max(e.force[1] for e in ests)), 2) > 0
    (50, True)
    >>> s.node_positions().shape
    (252, 3)
    """

    _W = np.array([[1.8, 0.6, -2.2, 0.9], [1.7, 0.6, 2.4, 0.9], [2.1, -2.0, 0.3, 0.8], [2.0, 2.1, 0.2, 0.8]])
    """mm³ per N (x, y, z) and per kPa of urethra pressure, one row per arm."""
    layout = BIP_LAYOUT  # a made-up BIP

    def __init__(self, rate_Hz: float = 77.0, duration_s: float | None = None, *, realtime: bool = True,
                 peak_force_N: float = 3.0, period_s: float = 4.0, subdivisions: int = 3, seed: int = 0):
        if not (0 < rate_Hz <= 10000):
            raise UserError(f"--rate-Hz must be in (0, 10000], got {rate_Hz}")
        self.geometry = ellipsoid_geometry(subdivisions=subdivisions)
        self.rate_Hz, self.duration_s, self.realtime = float(rate_Hz), duration_s, realtime
        self.peak_force_N, self.period_s = float(peak_force_N), float(period_s)
        self._rng = np.random.default_rng(seed)
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # force, xyz, ypr
        self._W_si = self._W * 1e-9  # m³ per N / per kPa

    def _deform(self, x: np.ndarray, force: np.ndarray, xyz: np.ndarray, ypr: np.ndarray) -> np.ndarray:
        dent = (force / 600.0) * np.exp(-np.sum((x - self.geometry.p_ext) ** 2, axis=-1) / (2 * 0.009 ** 2))[..., None]
        return (x + dent) @ _rot(ypr).T + xyz

    def _state(self, t: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        s = 0.5 * (1 - math.cos(2 * math.pi * t / self.period_s))
        f = self.peak_force_N * s * np.array([0.25 * math.sin(2 * math.pi * t / (2.3 * self.period_s)), 1.0,
                                              0.15 * math.cos(2 * math.pi * t / (3.1 * self.period_s))])
        p_ur = 2000.0 * 0.5 * (1 - math.cos(2 * math.pi * t / (5 * self.period_s)))  # Pa
        xyz = f / np.array([900.0, 450.0, 700.0])
        ypr = np.radians([-2.5 * f[0], 1.6 * f[2] - 0.8 * f[1], 0.3 * f[0]])
        return f, p_ur, xyz, ypr

    def __iter__(self) -> Iterator[Estimate]:
        from softphantom.pose import Pose6

        dt = 1.0 / self.rate_Hz
        n_max = None if self.duration_s is None else int(round(self.duration_s * self.rate_Hz))
        t0 = time.perf_counter()
        k = 0
        while n_max is None or k < n_max:
            skipped = 0
            if self.realtime:
                now = time.perf_counter() - t0
                if now < k * dt:
                    time.sleep(k * dt - now)
                else:
                    late = int((now - k * dt) / dt)
                    if late:
                        skipped = min(late, (n_max - k - 1) if n_max is not None else late)
                        k += skipped
            c0 = time.perf_counter()
            t = k * dt
            f, p_ur, xyz, ypr = self._state(t)
            act = np.array([*f, p_ur * 1e-3])
            pred = self._W_si @ act
            meas = pred + self._rng.normal(0.0, 0.03e-9, 4)
            shifts = {n: self._deform(p, f, xyz, ypr) - p for n, p in self.geometry.targets.items()}
            self._last = (f, xyz, ypr)
            est = Estimate(t=t, force=f, p_urethra=p_ur, pose=Pose6(xyz, ypr), target_shift=shifts,
                           volume_pred=pred, volume_meas=meas, cond_W=float(np.linalg.cond(self._W)),
                           qp_status="optimal", step_time=time.perf_counter() - c0, skipped=skipped,
                           status="ok", layout=self.layout)
            yield est
            k += 1

    def node_positions(self) -> np.ndarray | None:
        """Deformed surface positions (n, 3) m for the last estimate yielded."""
        if self._last is None:
            return self.geometry.nodes.copy()
        return self._deform(self.geometry.nodes, *self._last)


class AtlasField:
    """The deformed nodes of a model at given loads, from the atlases cached beside it
    (``MODEL/atlas/``, :mod:`softphantom.estimation.atlas`): the field an atlas estimator shows,
    for an estimate file replayed without its surfaces.

    ``pieces``: the atlases (:class:`~softphantom.estimation.atlas.map.Atlas`) built for this model
    (its node count) and the estimate's contact; a load is evaluated in the piece whose envelope
    holds it, else in the nearest piece, clamped to its envelope.
    """

    def __init__(self, pieces):
        self.pieces = tuple(pieces)
        boxes = [(np.r_[a.config.force_min_N, a.config.p_min_kPa * 1e3], np.r_[a.config.force_max_N, a.config.p_max_kPa * 1e3])
                 for a in self.pieces]
        self._lo, self._hi = np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes])

    @classmethod
    def from_model_dir(cls, model_dir: str | Path, n_nodes: int, contact: Any = None,
                       contact_radius_m: float | None = None) -> "AtlasField | None":
        """The atlases in ``model_dir``/atlas for a model of ``n_nodes`` nodes and (if given) the
        contact point and patch radius the estimates were made with; None if there is none (or
        they are for several contact points and ``contact`` does not say which)."""
        from softphantom.errors import SoftphantomError
        from softphantom.estimation.atlas.catalogue import atlases_of
        from softphantom.estimation.atlas.store import load_atlas

        pieces = []
        for path in atlases_of(model_dir):
            try:
                a = load_atlas(path)
            except SoftphantomError:  # a damaged or foreign file: the other atlases still serve
                continue
            prov = a.provenance or {}
            c = prov.get("contact")
            if a.x_rest.size != 3 * n_nodes or (contact is not None and c != contact):
                continue
            if contact_radius_m is not None and not math.isclose(float(prov.get("contact_radius_m", math.nan)),
                                                                  contact_radius_m, rel_tol=1e-6):
                continue
            pieces.append((str(c), a))
        if not pieces or len({c for c, _ in pieces}) > 1:
            return None
        return cls(a for _, a in pieces)

    def nodes(self, force: np.ndarray, p_Pa: float) -> np.ndarray | None:
        """(N, 3) m node positions at the load (force N, urethra pressure Pa); None if not finite."""
        load = np.r_[np.asarray(force, float), float(p_Pa)]
        if not np.all(np.isfinite(load)):
            return None
        clamped = np.clip(load, self._lo, self._hi)
        k = int(np.argmin(np.linalg.norm((clamped - load) / np.r_[1.0, 1.0, 1.0, 1e3], axis=1)))
        at = self.pieces[k]
        c = clamped[k]
        return at.nodes(at.coords(c[:3], c[3]))


class EstimateReplay:
    """Replay estimates from a session recording (``.mcap``) or an estimate CSV.

    Paced by ``t_s`` (times ``speed``; ``speed=0`` as fast as possible). A recording with
    ``/live/geometry`` and ``/live/surface`` also replays the deformation; otherwise ``geometry``
    comes from ``geometry`` (e.g. ``LiveGeometry.from_model``) or is None (plots only), and the
    surface shown is, by what is known: the deformation an ``atlas`` (:class:`AtlasField`) gives at
    each estimate's loads, else the rest shape moved rigidly by the estimated pose.
    ``surface_shows`` says which, for the page. ``model`` (a ``PhantomModel``), when ``geometry`` is
    not given: its surface, with the force at the file's contact point (its metadata's ``contact``),
    and the atlas from ``model_dir``/atlas for that contact (:meth:`AtlasField.from_model_dir`).
    ``layout``: the file's channels (its metadata's, :class:`~softphantom.records.channels.ChannelLayout`);
    a model of other channels is refused in one line naming both.
    """

    def __init__(self, path: str | Path, *, speed: float = 1.0, geometry: LiveGeometry | None = None,
                 atlas: AtlasField | None = None, model: Any = None, model_dir: str | Path | None = None):
        from softphantom.stream.recording import read_estimate_csv, read_recording

        path = Path(path)
        if not path.exists():
            raise UserError(f"replay file not found: {path}")
        self._surface: list[tuple[float, str]] = []
        recorded_note = None
        if path.suffix.lower() == ".mcap":
            rec = read_recording(path)
            self.messages = rec.estimates
            if not rec.complete:  # a killed writer: its complete chunks are read, the rest is gone
                import warnings

                from softphantom.records.session import TruncatedRecordingWarning

                warnings.warn(f"{path}: not closed cleanly: read up to its last complete chunk (byte {rec.bytes_read} "
                              f"of {path.stat().st_size}, {len(rec.estimates)} estimates), the rest dropped "
                              "(truncated file)", TruncatedRecordingWarning, stacklevel=2)
            self.meta: dict[str, Any] = {}
            if rec.geometry is not None and geometry is None:
                geometry = LiveGeometry.from_json(rec.geometry)
                recorded_note = rec.geometry.get("surface_shows")
            self._surface = [(float(m.get("t_s") or 0.0), m["positions_mm_f32_b64"]) for m in rec.surface
                             if "positions_mm_f32_b64" in m]
            self.layout = rec.layout
        else:
            from softphantom.stream.recording import estimate_file_layout

            self.meta, self.messages = read_estimate_csv(path)
            self.layout = estimate_file_layout(path, self.meta, self.messages[0] if self.messages else ())
        self.arm_names, self.cavity_names = self.layout.sensing, self.layout.actuated
        if not self.messages:
            raise FileFormatError(f"{path}: no estimates to replay")
        theirs = getattr(model, "layout", None)
        if geometry is None and theirs is not None and theirs.sensing != self.arm_names:
            raise UserError(f"replay {path}: its arms ({', '.join(self.arm_names)}) are not the model's "
                            f"({', '.join(theirs.sensing)})")
        if geometry is None and theirs is not None and theirs.actuated != self.cavity_names:
            raise UserError(f"replay {path}: its internal cavities ({', '.join(self.cavity_names) or 'none'}) are "
                            f"not the model's ({', '.join(theirs.actuated) or 'none'})")
        if geometry is None and model is not None:
            contact = self.meta.get("contact")
            radius_mm = self.meta.get("contact_radius_mm")
            radius = float(radius_mm) * 1e-3 if isinstance(radius_mm, (int, float)) else None
            points = getattr(model, "p_ext", {}) or {}
            geometry = LiveGeometry.from_model(model, contact if contact in points else "on-centre", radius)
            recorded_note = None
            if atlas is None and model_dir is not None and not self._surface:
                atlas = AtlasField.from_model_dir(model_dir, len(model.nodes), contact, radius)
        self.geometry = geometry  # type: ignore[assignment]
        # the atlas tabulates the urethra's pressure alone
        self.atlas = atlas if geometry is not None and not self._surface and self.cavity_names == ("urethra",) else None
        if geometry is None:
            self.surface_shows = None
        elif self._surface:
            self.surface_shows = recorded_note
        elif self.atlas is not None:
            self.surface_shows = "deformation from the model's atlas at the estimated loads"
        else:
            self.surface_shows = ("rest shape moved rigidly by the estimated pose (no atlas for this model and "
                                  "contact: the local deformation is not shown)")
        self.speed = float(speed)
        self._t = -math.inf
        self._last: Estimate | None = None
        self._pos: np.ndarray | None = None

    def __iter__(self) -> Iterator[Estimate]:
        t_first = float(self.messages[0].get("t_s") or 0.0)
        w0 = time.perf_counter()
        for m in self.messages:
            est = message_to_estimate(m, self.layout)
            if self.speed > 0:
                wait = (est.t - t_first) / self.speed - (time.perf_counter() - w0)
                if wait > 0:
                    time.sleep(wait)
            self._t = est.t
            if np.all(np.isfinite(est.force)) and np.all(np.isfinite(est.pose.xyz)):
                self._last = est  # a link event's marker has no numbers: the surface stays
            yield est

    def node_positions(self) -> np.ndarray | None:
        """The surface for the last estimate: the recorded one nearest before it; else from the
        atlas or the pose (the class docstring); None without geometry."""
        if self.geometry is None:
            return None
        if self._surface:
            times = [t for t, _ in self._surface]
            i = int(np.searchsorted(times, self._t, side="right")) - 1
            return decode_positions_mm(self._surface[max(i, 0)][1])
        est = self._last
        if est is None:
            return self.geometry.nodes.copy()
        if self.atlas is not None and (x := self.atlas.nodes(est.force, est.p_urethra)) is not None:
            return x[self.geometry.node_index]
        R = _rot(np.asarray(est.pose.ypr, float))  # the model frame's origin is the bulb centre at rest
        return self.geometry.nodes @ R.T + np.asarray(est.pose.xyz, float)


class EstimatorSource:
    """The real estimator as a live source: each sensor sample of ``sensor`` (a
    :class:`~softphantom.sensing.sources.SensorSource`) through ``estimator``
    (:class:`~softphantom.estimation.Estimator`) for ``model``.

    ``live=True`` (a board): the newest sample is estimated and the ones it overtook are counted as
    skipped — acquisition never waits for the estimator. ``live=False`` (virtual phantom, replay):
    every sample is estimated, paced to the samples' clock divided by ``speed`` (0: as fast as
    possible). Closing it closes the estimator and the sensor source.
    """

    def __init__(self, model: Any, sensor: Any, estimator: Any, *, live: bool, speed: float = 1.0,
                 p_ext: str = "on-centre") -> None:
        radius = getattr(getattr(estimator, "config", None), "contact_radius_m", None)
        self.geometry = LiveGeometry.from_model(model, p_ext, radius)
        self.layout = estimator.layout
        self.arm_names, self.cavity_names = self.layout.sensing, self.layout.actuated
        self._sensor, self._est = sensor, estimator
        self.live, self.speed = bool(live), float(speed)
        self._last_m = None

    def _samples(self) -> Iterator[tuple[Any, int]]:
        from softphantom.estimation.stream import iter_samples

        samples = iter_samples(self._sensor, self.live, idle=True)
        if self.live:
            yield from samples
            return
        t_first, w0 = None, time.perf_counter()
        for m, _ in samples:
            if self.speed > 0:
                t_first = m.t if t_first is None else t_first
                wait = (m.t - t_first) / self.speed - (time.perf_counter() - w0)
                if wait > 0:
                    time.sleep(wait)
            yield m, 0

    def __iter__(self) -> Iterator[Estimate]:
        from softphantom.estimation.stream import EventMarkers

        # link events (unplugged, silent, resumed, ...) reach the page, the stream and the
        # recording as marker estimates (status "event:<kind>: ...", numbers null)
        markers = EventMarkers(self._sensor, getattr(self._est, "target_names", ()), self.layout)
        for m, skipped in self._samples():
            if m is None:               # a live source gave nothing for a while
                yield from markers.due(None)
                continue
            yield from markers.due(m.t)
            self._last_m = m
            yield self._est.step(m, skipped=skipped)
        yield from markers.due(None)

    def node_positions(self) -> np.ndarray | None:
        return self._est.node_positions()

    def last_measurement(self) -> Any:
        return self._last_m

    def close(self) -> None:
        self._est.close()
        self._sensor.close()
