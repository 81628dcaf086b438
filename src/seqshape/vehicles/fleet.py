"""The fleet generator: every class a driving dataset annotates, sized like the real fleet.

* `fleet_vehicle(kind_or_class, seed)`: one vehicle of a fine kind (`FLEET_KINDS`) or of a
  class (`VEHICLE_CLASSES`; the kind is then drawn from the class's mix with the seed);
* `fleet_library(n, seed, mix=None)`: ``n`` vehicles with exact per-kind quotas of a realistic
  annotation mix (`DEFAULT_MIX`), in a seeded order;
* `vehicle_from_source(source)`: rebuild a vehicle from its ``source`` string, for the original
  procedural kinds (``procedural:<kind>:<seed>``) and the fleet (``fleet:<kind>:<seed>``).

Each fleet `Vehicle` has ``kind`` (fine kind), ``cls`` (class), ``face_labels`` (per-face
material codes, `seqshape.vehicles.base.FACE_LABELS`; also in ``mesh.metadata["face_labels"]``)
and ``box_size`` (extents without the side mirrors, as annotators draw boxes). The original
`vehicle_library` / `procedural_vehicle` are untouched: their meshes are the same as before.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import asdict

import numpy as np

from seqshape.errors import ConfigError
from seqshape.vehicles.base import VEHICLE_CLASSES, Vehicle, centre_on_bbox
from seqshape.vehicles.car_details import build_car
from seqshape.vehicles.car_kinds import CAR_KINDS, sample_car_params
from seqshape.vehicles.heavy import HEAVY_BUILDERS
from seqshape.vehicles.parts import assemble
from seqshape.vehicles.procedural import procedural_vehicle

#: fine kind -> class, in class order.
FLEET_KINDS: dict[str, str] = {
    "city_car": "car", "hatchback": "car", "sedan": "car", "estate": "car", "coupe": "car",
    "mpv": "car", "crossover": "car", "suv": "car", "pickup": "car",
    "panel_van": "van", "high_roof_van": "van",
    "box_truck": "truck", "tractor": "truck", "flatbed": "truck",
    "city_bus": "bus", "coach": "bus",
    "semi_trailer": "trailer", "car_trailer": "trailer",
}

#: share of each class among annotated vehicles (rounded from the class counts of nuScenes,
#: Argoverse 2 and KITTI annotations; docs/vehicles.md).
CLASS_MIX = {"car": 0.78, "van": 0.08, "truck": 0.07, "bus": 0.03, "trailer": 0.04}

#: share of each kind within its class (car segments: blended US/EU registrations).
KIND_MIX = {
    "city_car": 0.06, "hatchback": 0.16, "sedan": 0.22, "estate": 0.06, "coupe": 0.04,
    "mpv": 0.06, "crossover": 0.20, "suv": 0.12, "pickup": 0.08,
    "panel_van": 0.6, "high_roof_van": 0.4,
    "box_truck": 0.45, "tractor": 0.35, "flatbed": 0.20,
    "city_bus": 0.7, "coach": 0.3,
    "semi_trailer": 0.7, "car_trailer": 0.3,
}


#: car segment shares by region (approximate shares of recent new-car registrations: the US
#: market is dominated by crossovers, SUVs and pickups, Europe by hatchbacks and crossovers).
CAR_MIX_BY_REGION = {
    "us": {"city_car": 0.02, "hatchback": 0.05, "sedan": 0.18, "estate": 0.01, "coupe": 0.03,
           "mpv": 0.05, "crossover": 0.30, "suv": 0.18, "pickup": 0.18},
    "eu": {"city_car": 0.09, "hatchback": 0.27, "sedan": 0.08, "estate": 0.10, "coupe": 0.02,
           "mpv": 0.04, "crossover": 0.30, "suv": 0.08, "pickup": 0.02},
}


def _mix(car_mix: dict[str, float] | None = None) -> dict[str, float]:
    kind_mix = {**KIND_MIX, **(car_mix or {})}
    return {k: CLASS_MIX[c] * kind_mix[k] for k, c in FLEET_KINDS.items()}


#: share of each fine kind in `fleet_library` by default (class share x kind share).
DEFAULT_MIX = _mix()

#: named mixes for `fleet_library(mix=...)`: ``"default"`` (blend), ``"us"``, ``"eu"`` (same
#: class shares, car segments of that region).
MIXES = {"default": DEFAULT_MIX, **{r: _mix(m) for r, m in CAR_MIX_BY_REGION.items()}}


def _kind_seed(kind: str) -> int:
    return zlib.crc32(kind.encode()) & 0xFFFF


def _kinds_of(cls: str) -> list[str]:
    return [k for k, c in FLEET_KINDS.items() if c == cls]


def _resolve_kind(kind_or_class: str, seed: int) -> str:
    if kind_or_class in FLEET_KINDS:
        return kind_or_class
    if kind_or_class in VEHICLE_CLASSES:
        kinds = _kinds_of(kind_or_class)
        w = np.array([KIND_MIX[k] for k in kinds])
        rng = np.random.default_rng([int(seed), 0xC1A5])
        return kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
    raise ConfigError(f"unknown vehicle kind or class {kind_or_class!r}; choose a class from "
                      f"{VEHICLE_CLASSES} or a kind from {tuple(FLEET_KINDS)}")


def fleet_vehicle(kind_or_class: str, seed: int) -> Vehicle:
    """One fleet vehicle of a fine kind (e.g. ``"estate"``) or a class (e.g. ``"truck"``).

    Deterministic for (kind, seed); ``source`` is ``fleet:<kind>:<seed>`` with the fine kind.
    """
    if int(seed) < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    kind = _resolve_kind(kind_or_class, seed)
    rng = np.random.default_rng([int(seed), _kind_seed(kind)])
    if kind in CAR_KINDS:
        params = sample_car_params(kind, rng)
        parts, _ = build_car(params)
        meta = asdict(params)
    else:
        parts, meta = HEAVY_BUILDERS[kind](rng)
    mesh, labels = assemble(parts)
    in_box = np.concatenate([np.full(len(p.vertices), p.in_box) for p in parts])
    lo, hi = mesh.bounds
    centre_on_bbox(mesh)
    verts = np.asarray(mesh.vertices)[in_box]
    box = verts.max(axis=0) - verts.min(axis=0)
    mesh.metadata["params"] = {k: v for k, v in meta.items() if k != "extra"}
    mesh.metadata["build_to_canonical"] = -(lo + hi) / 2.0  # add to build-frame points
    mesh.metadata["face_labels"] = labels
    return Vehicle(vehicle_id=f"fleet-s{int(seed)}-{kind}", mesh=mesh, kind=kind,
                   source=f"fleet:{kind}:{int(seed)}", cls=FLEET_KINDS[kind],
                   face_labels=labels, box_size=box)


def _mix_weights(mix: Mapping[str, float] | str | None) -> dict[str, float]:
    if mix is None:
        return dict(DEFAULT_MIX)
    if isinstance(mix, str):
        if mix not in MIXES:
            raise ConfigError(f"unknown mix {mix!r}; choose from {tuple(MIXES)} or give a "
                              "mapping of classes / kinds to weights")
        return dict(MIXES[mix])
    out: dict[str, float] = {}
    for name, w in mix.items():
        if not (np.isfinite(w) and w >= 0):
            raise ConfigError(f"mix weight of {name!r} must be >= 0, got {w}")
        if name in FLEET_KINDS:
            out[name] = out.get(name, 0.0) + float(w)
        elif name in VEHICLE_CLASSES:
            kinds = _kinds_of(name)
            tot = sum(KIND_MIX[k] for k in kinds)
            for k in kinds:
                out[k] = out.get(k, 0.0) + float(w) * KIND_MIX[k] / tot
        else:
            raise ConfigError(f"unknown kind or class {name!r} in mix; classes "
                              f"{VEHICLE_CLASSES}, kinds {tuple(FLEET_KINDS)}")
    if sum(out.values()) <= 0:
        raise ConfigError("mix weights sum to 0")
    return out


def kind_quotas(n: int, mix: Mapping[str, float] | str | None = None) -> dict[str, int]:
    """Exact number of vehicles per kind for a library of ``n`` (largest remainders)."""
    w = _mix_weights(mix)
    kinds = [k for k in FLEET_KINDS if w.get(k, 0) > 0]
    share = np.array([w[k] for k in kinds]) / sum(w[k] for k in kinds)
    raw = share * n
    count = np.floor(raw).astype(int)
    order = np.argsort(-(raw - count), kind="stable")
    count[order[: n - count.sum()]] += 1
    return {k: int(c) for k, c in zip(kinds, count, strict=True) if c > 0}


def fleet_library(n: int, seed: int = 0, mix: Mapping[str, float] | str | None = None
                  ) -> list[Vehicle]:
    """``n`` fleet vehicles with per-kind quotas of ``mix`` (default `DEFAULT_MIX`).

    ``mix`` is the name of a preset (`MIXES`: ``"default"``, ``"us"``, ``"eu"``) or maps kinds
    and/or classes to weights (a class spreads over its kinds by `KIND_MIX`), e.g.
    ``{"car": 0.6, "truck": 0.2, "bus": 0.2}``. The kinds are shuffled with
    ``seed``; ids are ``fleet-<index:04d>-<kind>`` for seed 0 and ``fleet-s<seed>-<index:04d>-<kind>``
    otherwise, so libraries of different seeds can be trained on together; each ``source``
    rebuilds its vehicle.
    """
    if n < 0:
        raise ConfigError(f"n must be >= 0, got {n}")
    quotas = kind_quotas(n, mix)
    kinds = [k for k, c in quotas.items() for _ in range(c)]
    rng = np.random.default_rng([int(seed), 0xF1EE7])
    kinds = [kinds[i] for i in rng.permutation(len(kinds))]
    seeds = np.random.SeedSequence([int(seed), 0xF1EE]).generate_state(max(n, 1), np.uint32)
    prefix = "" if int(seed) == 0 else f"s{int(seed)}-"
    out = []
    for i, kind in enumerate(kinds):
        v = fleet_vehicle(kind, int(seeds[i]))
        v.vehicle_id = f"fleet-{prefix}{i:04d}-{kind}"
        out.append(v)
    return out


def vehicle_from_source(source: str) -> Vehicle:
    """Rebuild a procedural (``procedural:<kind>:<seed>``) or fleet (``fleet:<kind>:<seed>``)
    vehicle from its ``source`` string."""
    parts = str(source).split(":")
    if len(parts) != 3 or parts[0] not in ("procedural", "fleet") or not parts[2].isdigit():
        raise ConfigError(f"not a procedural or fleet vehicle source: {source!r} (expected "
                          "'procedural:<kind>:<seed>' or 'fleet:<kind>:<seed>')")
    builder = procedural_vehicle if parts[0] == "procedural" else fleet_vehicle
    return builder(parts[1], int(parts[2]))
