"""The sweep file (TOML): which parameters vary, how they are sampled, and how a variant is evaluated.

A parameter is a dotted path:

* into the design file (:func:`~softphantom.design.design_to_dict`): ``bulb.semi_axes_mm[2]``,
  ``arms.front_zpos.direction[1]``, ``arms.*.radius_mm`` (``*``: every entry of that table gets
  the value), ``urethra.radius_mm``, ``mesh.size_mm``, the silicone ``materials.*.E_kPa``,
  ``materials.ecoflex_00_50.law``, ``region_materials.bulb``; ``arms.<arm>.cavity_length_mm`` sets
  the cavity's cylinder length (its volume follows from the capsule, radius ``radius_mm − wall_mm``);
* ``mesh_size_mm``: the bulb element size, arm and cavity sizes scaled with it (as ``--mesh-size-mm``);
* ``element_order``: 1 (4-node tets) or 2 (10-node tets; about ten times the cost of a variant);
  default the base design's;
* ``sensing.tube_length_m``, ``sensing.tube_id_mm``, ``sensing.osr``: the pneumatic line of every arm.

Each parameter is a table: ``{min, max}`` (continuous; ``log = true`` samples it log-uniformly,
``steps = n`` gives n grid points) or ``{values = [...]}`` (a list). Methods: ``grid`` (the
product of all lists), ``random`` and ``lhs`` (Latin hypercube, :mod:`scipy.stats.qmc`),
``samples`` variants, seeded.

>>> cfg = sweep_config_from_dict({"sweep": {"method": "grid"},
...     "parameters": {"arms.*.radius_mm": {"values": [5.5, 6.0]}, "sensing.tube_length_m": {"min": 1, "max": 12, "steps": 2}}})
>>> [v.params for v in cfg.variants()]
[{'arms.*.radius_mm': 5.5, 'sensing.tube_length_m': 1.0}, {'arms.*.radius_mm': 5.5, 'sensing.tube_length_m': 12.0}, {'arms.*.radius_mm': 6.0, 'sensing.tube_length_m': 1.0}, {'arms.*.radius_mm': 6.0, 'sensing.tube_length_m': 12.0}]
>>> sweep_config_from_dict({"parameters": {"arms.front_zpos.colour": {"values": [1]}}})
Traceback (most recent call last):
...
softphantom.errors.UserError: parameters."arms.front_zpos.colour": unknown parameter (arms.front_zpos has axis_point_mm, cavity_length_mm, cavity_offset_mm, cavity_volume_mm3, direction, embed_mm, junction_fillet_mm, length_mm, radius_mm, wall_mm)
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import model_validator

from softphantom.design import BIPDesign, design_to_dict, load_design
from softphantom.errors import UserError
from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M
from softphantom.schema import Field, FileModel, parse, refuse

METHODS = ("grid", "random", "lhs")
#: The most variants a study lists: each is meshed and linearized (seconds of CPU), and its record
#: (the full design dict) takes about VARIANT_BYTES of memory.
MAX_VARIANTS = 100_000
VARIANT_BYTES = 20_000
#: Bumped when what a variant computes changes, so cached rows of older code are not reused.
EVAL_VERSION = 3
_INDEX = re.compile(r"^(?P<key>[A-Za-z0-9_]+)(\[(?P<i>[0-9]+)\])?$")
Positive = Annotated[float, Field(gt=0)]
Count = Annotated[int, Field(ge=1)]


class _Fixed(FileModel):
    """The settings beside the design (``[fixed]``, or swept by these names) and their defaults."""

    mesh_size_mm: Positive = 12.0
    element_order: Literal[1, 2] | None = None  # 1: 4-node tets, 2: 10-node; None: the base design's
    tube_length_m: Positive = Field(12.0, alias="sensing.tube_length_m")
    tube_id_mm: Positive = Field(1.2, alias="sensing.tube_id_mm")
    osr: Count = Field(100, alias="sensing.osr")


EXTRA_PARAMS = _Fixed().model_dump(by_alias=True)
DIRECTIONS = {"xpos": (1, 0, 0), "xneg": (-1, 0, 0), "ypos": (0, 1, 0), "yneg": (0, -1, 0),
              "zpos": (0, 0, 1), "zneg": (0, 0, -1)}


@dataclass(frozen=True)
class ParamSpec:
    """One swept parameter: a list of ``values`` or a continuous ``[lo, hi]`` (``log``, ``steps``)."""

    path: str
    values: tuple | None = None
    lo: float | None = None
    hi: float | None = None
    log: bool = False
    steps: int = 3

    @property
    def continuous(self) -> bool:
        return self.values is None

    def grid(self) -> list:
        if self.values is not None:
            return list(self.values)
        if self.log:
            return [float(v) for v in np.geomspace(self.lo, self.hi, self.steps)]
        return [float(v) for v in np.linspace(self.lo, self.hi, self.steps)]

    def from_unit(self, u: float):
        """The value at ``u`` in [0, 1) (a uniform sample or a Latin-hypercube coordinate)."""
        if self.values is not None:
            return self.values[min(int(u * len(self.values)), len(self.values) - 1)]
        if self.log:
            return float(math.exp(math.log(self.lo) + u * (math.log(self.hi) - math.log(self.lo))))
        return float(self.lo + u * (self.hi - self.lo))


@dataclass(frozen=True)
class EvalSettings:
    """How a variant is evaluated: contact point and patch, the probe load along each of the six
    axis directions (N), the force cap of the range search, the transducer limit used for
    saturation (the arm transducer's rated range)."""

    contact: str = "on-centre"
    contact_radius_mm: float = DEFAULT_CONTACT_RADIUS_M * 1e3  # the one contact model's default patch
    probe_force_N: float = 3.0
    directions: tuple[str, ...] = tuple(DIRECTIONS)
    max_force_N: float = 50.0

    def as_dict(self) -> dict:
        return {"contact": self.contact, "contact_radius_mm": self.contact_radius_mm,
                "probe_force_N": self.probe_force_N, "directions": list(self.directions),
                "max_force_N": self.max_force_N}


@dataclass(frozen=True)
class Variant:
    """One point of the study: the swept values (``params``, by path), the full design dict and
    the extra settings (mesh size, tube, material) it resolves to, and its cache key."""

    index: int
    params: dict
    design: dict
    extra: dict
    settings: EvalSettings

    @property
    def key(self) -> str:
        blob = json.dumps({"v": EVAL_VERSION, "design": self.design, "extra": self.extra,
                           "eval": self.settings.as_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]


@dataclass(frozen=True)
class OptimizeSettings:
    """``--optimize``: minimize the worst-axis force resolution (N per count) over the continuous
    parameters, subject to ``min_range_N`` (smallest force, any axis direction, that saturates a
    transducer) and ``max_silicone_mL`` (meshed silicone volume); differential evolution,
    ``popsize`` × (number of parameters) candidates a generation evaluated in parallel."""

    maxiter: int = 8
    popsize: int = 4
    seed: int = 1
    min_range_N: float = 0.0
    max_silicone_mL: float = math.inf
    objective: str = "res_force_worst_N"


@dataclass(frozen=True)
class SweepConfig:
    name: str = "sweep"
    method: str = "lhs"
    samples: int = 20
    seed: int = 1
    base: dict = field(default_factory=lambda: design_to_dict(BIPDesign()))
    params: tuple[ParamSpec, ...] = ()
    fixed: dict = field(default_factory=dict)  # extra settings not swept (mesh_size_mm, tube, material)
    settings: EvalSettings = EvalSettings()
    optimize: OptimizeSettings = OptimizeSettings()

    def resolve(self, index: int, values: dict) -> Variant:
        """The variant with ``values`` (path -> value) applied to the base design and settings."""
        design = copy.deepcopy(self.base)
        extra = {k: v for k, v in EXTRA_PARAMS.items()}
        extra.update(self.fixed)
        for path, v in values.items():
            v = v.item() if isinstance(v, np.generic) else v
            if path in EXTRA_PARAMS:
                extra[path] = v
            else:
                apply_path(design, path, v)
        if extra.get("element_order") is not None:  # a design setting given beside the others
            apply_path(design, "mesh.element_order", int(extra["element_order"]))
        return Variant(index, {k: (v.item() if isinstance(v, np.generic) else v) for k, v in values.items()},
                       design, extra, self.settings)

    def count(self) -> int:
        """How many variants :meth:`variants` lists (computed without listing them)."""
        if not self.params:
            return 1
        if self.method == "grid":
            return math.prod(len(p.values) if p.values is not None else p.steps for p in self.params)
        return self.samples

    def variants(self) -> list[Variant]:
        """All variants of the study, in a deterministic order."""
        if not self.params:
            return [self.resolve(0, {})]
        names = [p.path for p in self.params]
        if self.method == "grid":
            combos = list(itertools.product(*(p.grid() for p in self.params)))
        else:
            if self.method == "lhs":
                from scipy.stats import qmc

                u = qmc.LatinHypercube(d=len(self.params), seed=self.seed).random(self.samples)
            else:
                u = np.random.default_rng(self.seed).random((self.samples, len(self.params)))
            combos = [tuple(p.from_unit(float(x)) for p, x in zip(self.params, row)) for row in u]
        return [self.resolve(i, dict(zip(names, c))) for i, c in enumerate(combos)]


def _steps(name: str, key: str):
    m = _INDEX.match(key)
    if m is None:
        raise UserError(f"parameters.{name}: malformed part {key!r} (name or name[index])")
    return m.group("key"), (int(m.group("i")) if m.group("i") is not None else None)


def apply_path(design: dict, path: str, value: Any, _name: str | None = None) -> None:
    """Set ``path`` (dotted, ``[i]`` indexes a vector, ``*`` every entry of a table: ``arms.*``,
    ``materials.*``) in a design dict."""
    parts = path.split(".")
    if "*" in parts:
        i = parts.index("*")
        node: Any = design
        for part in parts[:i]:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or not node:
            raise UserError(f"parameters.{json.dumps(_name or path)}: {'.'.join(parts[:i]) or 'the design'} "
                            "is not a table of entries for '*'")
        for key in list(node):
            apply_path(design, ".".join([*parts[:i], key, *parts[i + 1:]]), value, _name or path)
        return
    name = json.dumps(_name or path)
    if parts[0] == "arms" and len(parts) == 3 and parts[2] == "cavity_length_mm":
        arm = design.get("arms", {}).get(parts[1])
        if arm is None:
            raise UserError(f"parameters.{name}: unknown arm {parts[1]!r} (one of {', '.join(design.get('arms', {}))}, *)")
        r = float(arm["radius_mm"]) - float(arm["wall_mm"])
        arm["cavity_volume_mm3"] = math.pi * r * r * float(value) + 4.0 / 3.0 * math.pi * r**3
        return
    node = design
    for depth, part in enumerate(parts):
        key, idx = _steps(name, part)
        last = depth == len(parts) - 1
        if not isinstance(node, dict) or key not in node:
            where = ".".join(parts[:depth]) or "the design"
            have = sorted(node) if isinstance(node, dict) else []
            if where.startswith("arms.") and depth == 2:
                have = sorted([*have, "cavity_length_mm"])
            raise UserError(f"parameters.{name}: unknown parameter ({where} has {', '.join(map(str, have))})")
        if idx is not None:
            vec = node[key]
            if not isinstance(vec, list) or idx >= len(vec):
                raise UserError(f"parameters.{name}: {key} has no element [{idx}]")
            if last:
                vec[idx] = value
                return
            node = vec[idx]
        elif last:
            node[key] = list(value) if isinstance(value, (list, tuple)) else value
            return
        else:
            node = node[key]


class _Sweep(FileModel):
    name: str = "sweep"
    method: Literal[METHODS] = "lhs"
    samples: Count = 20
    seed: Annotated[int, Field(ge=0)] = 1
    design: str | None = None  # a design file, relative to the sweep file


class _Evaluate(FileModel):
    contact: str = EvalSettings.contact
    contact_radius_mm: Positive = EvalSettings.contact_radius_mm
    probe_force_N: Positive = EvalSettings.probe_force_N
    directions: Annotated[list[Literal[tuple(DIRECTIONS)]], Field(min_length=1)] = list(DIRECTIONS)
    max_force_N: Positive = EvalSettings.max_force_N


class _Param(FileModel):
    values: Annotated[list[Any], Field(min_length=1)] | None = None
    min: float | None = None
    max: float | None = None
    log: bool = False
    steps: Count = 3

    @model_validator(mode="after")
    def _range(self):
        given = self.model_fields_set
        if self.values is not None:
            if given - {"values"}:
                raise refuse("give either values or min/max, not both")
        elif self.min is None or self.max is None:
            raise refuse("needs min and max (or values)")
        elif not self.max >= self.min:
            raise refuse(f"max {self.max:g} is below min {self.min:g}")
        elif self.log and self.min <= 0:
            raise refuse("log sampling needs min > 0")
        return self


class _Optimize(FileModel):
    maxiter: Count = OptimizeSettings.maxiter
    popsize: Count = OptimizeSettings.popsize
    seed: Annotated[int, Field(ge=0)] = OptimizeSettings.seed
    min_range_N: float = OptimizeSettings.min_range_N
    max_silicone_mL: float = OptimizeSettings.max_silicone_mL
    objective: str = OptimizeSettings.objective


class _SweepFile(FileModel):
    sweep: _Sweep = _Sweep()
    evaluate: _Evaluate = _Evaluate()
    fixed: _Fixed = _Fixed()
    parameters: dict[str, _Param] = {}
    optimize: _Optimize = _Optimize()


def sweep_config_from_dict(data: dict, base_dir: Path | None = None) -> SweepConfig:
    """A :class:`SweepConfig` from the parsed sweep file; every bad key raises a one-line UserError."""
    f = parse(_SweepFile, data, top="sweep file")
    base = BIPDesign()
    if f.sweep.design is not None:
        p = Path(f.sweep.design)
        base = load_design(p if p.is_absolute() or base_dir is None else base_dir / p)
    base_dict = design_to_dict(base)
    params = tuple(ParamSpec(k, values=tuple(v.values)) if v.values is not None else
                   ParamSpec(k, lo=v.min, hi=v.max, log=v.log, steps=v.steps) for k, v in f.parameters.items())
    probe = copy.deepcopy(base_dict)
    for p in params:  # unknown paths fail here, before any work
        if p.path not in EXTRA_PARAMS:
            apply_path(probe, p.path, p.values[0] if p.values else p.lo)
    ev = f.evaluate.model_dump()
    cfg = SweepConfig(
        name=f.sweep.name, method=f.sweep.method, samples=f.sweep.samples, seed=f.sweep.seed, base=base_dict,
        params=params, fixed=dict(data.get("fixed", {})),  # as written: part of each variant's cache key
        settings=EvalSettings(**{**ev, "directions": tuple(ev["directions"])}),
        optimize=OptimizeSettings(**f.optimize.model_dump()),
    )
    check_size(cfg)
    return cfg


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


def check_size(cfg: SweepConfig) -> None:
    """Refuse a study of more than :data:`MAX_VARIANTS` variants before any of them is listed,
    naming the field that sets the count and the memory listing them would take.

    >>> check_size(SweepConfig(method="lhs", samples=10**12, params=(ParamSpec("mesh_size_mm", lo=8, hi=12),)))
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: sweep.samples = 1000000000000: 1e+12 variants would take 17.8 PiB to list; a study has at most 100,000 (lower it)
    """
    n = cfg.count()
    if n <= MAX_VARIANTS:
        return
    if cfg.method == "grid":
        field_ = "parameters (grid " + " × ".join(
            f"{json.dumps(p.path)} {len(p.values) if p.values is not None else p.steps}" for p in cfg.params) + ")"
    else:
        field_ = f"sweep.samples = {cfg.samples}"
    count = f"{n:,}" if n < 10**9 else f"{n:.3g}"
    raise UserError(f"{field_}: {count} variants would take {_bytes(n * VARIANT_BYTES)} to list; a study has at "
                    f"most {MAX_VARIANTS:,} (lower it)")


def load_sweep_config(path: str | Path) -> SweepConfig:
    """Read a sweep file (TOML); a missing or malformed file is a one-line UserError naming it."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None
    if not data:  # a blank file would run one variant of the default design
        raise UserError(f"{path}: empty sweep file (no [sweep], no [parameters]; docs/sweep.md)")
    return sweep_config_from_dict(data, path.parent)
