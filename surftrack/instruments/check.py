"""``surftrack instruments --check``: what a description will do in synthesis and tracking, before any.

Per part: size, watertightness, keypoints (given or derived). Per pair of parts: contact at the rest
configuration (then not tested), the rule that applies (:mod:`surftrack.instruments.contacts`) and how
often random joint states over its reach (:meth:`Instrument.reach`, what synthesis draws from) collide
under it, which predicts synthesis's ``part_collision`` rejections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from surftrack.instruments.contacts import ContactRule, collision_manager, contact_depths
from surftrack.instruments.kinematics import JOINT_NAMES, JointState
from surftrack.instruments.library import Instrument

#: A tracked part longer than this (mm) is most likely a whole shaft tube: a few centimetres of it are
#: ever in view, and a 300 mm "diameter" makes ADD-10's threshold meaningless.
LONG_PART_MM = 80.0
#: Suggested length of the tracked shaft piece (the procedural shafts keep 40 mm).
SUGGESTED_SHAFT_MM = 40.0


@dataclass
class PairReport:
    parts: tuple[str, str]
    linked: bool
    rest_depth_mm: float | None      # penetration at rest, None when not in contact
    colliding_fraction: float        # of the random joint states, under the rule
    max_depth_mm: float              # deepest penetration seen over them (0 when never in contact)


@dataclass
class InstrumentCheck:
    instrument: str
    lines: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    pairs: list[PairReport] = field(default_factory=list)


def size_warnings(instrument: Instrument) -> list[str]:
    """One warning per part longer than :data:`LONG_PART_MM` (a whole shaft tube taken as a part) and per
    joint that turns a part but has no limit (it is then held at 0 in synthesis)."""
    out = []
    used = {k for j in instrument.chain.joints.values() for k, c in j.coefficients.items() if c}
    for name in sorted(used - set(instrument.limits.ranges)):
        out.append(f"{instrument.source or instrument.name}: joint {name!r} turns a part but has no limit in "
                   f"joint_limits_deg: synthesis holds it at 0")
    for name, part in instrument.parts.items():
        length = float(part.mesh.extents.max())
        if length > LONG_PART_MM:
            out.append(f"{instrument.source or instrument.name}: part {name!r} is {length:.0f} mm long: if it is "
                       f"the whole shaft tube, keep its distal end as the tracked part with `shaft_length_mm: "
                       f"{SUGGESTED_SHAFT_MM:g}` in its mesh (the rest is still rendered); a part's size sets "
                       f"its ADD-10 threshold")
    return out


def random_joint_states(instrument: Instrument, count: int, seed: int = 0) -> list[JointState]:
    """``count`` joint states uniform over the instrument's reach (what synthesis draws from)."""
    rng = np.random.default_rng(seed)
    reach = instrument.reach()
    return [JointState(*(float(rng.uniform(*reach[n])) for n in JOINT_NAMES)) for _ in range(count)]


def check_instrument(instrument: Instrument, samples: int = 200, seed: int = 0) -> InstrumentCheck:
    """The report of ``surftrack instruments --check`` for one instrument (``samples`` random joint states)."""
    out = InstrumentCheck(instrument.name)
    where = instrument.source or instrument.name
    derived = set(instrument.derived_tips)
    out.lines.append(f"{instrument.name} ({where})")
    for name, part in instrument.parts.items():
        length = float(part.mesh.extents.max())
        kps = ", ".join(f"{k}{' (derived)' if k == 'tip' and name in derived else ''}"
                        for k in part.keypoints) or "none"
        out.lines.append(f"  part {name:12s} {len(part.mesh.faces):6d} faces, {length:6.1f} mm long, "
                         f"diameter {part.diameter_max_pairwise:6.1f} mm, watertight={part.mesh.is_watertight}; "
                         f"keypoints: {kps}")
        if not part.mesh.is_watertight:
            out.lines.append(f"    note: {name} is not watertight; rendering and training do not need it, "
                             f"but its volume and inside tests are undefined")
    out.warnings += size_warnings(instrument)
    rule = ContactRule.of(instrument)
    manager = collision_manager({n: p.mesh for n, p in instrument.parts.items()})
    pairs = [tuple(sorted(p)) for p in combinations(instrument.parts, 2)]
    hits = {p: 0 for p in pairs}
    deepest = {p: 0.0 for p in pairs}
    for q in random_joint_states(instrument, samples, seed):
        for (a, b), depth in contact_depths(manager, instrument.forward(np.eye(4), q)).items():
            deepest[(a, b)] = max(deepest[(a, b)], depth)
            hits[(a, b)] += rule.rejects(a, b, depth)
    out.lines.append(f"  pairs of parts ({samples} random joint states over the instrument's reach):")
    for a, b in pairs:
        rep = PairReport((a, b), (a, b) in rule.linked, rule.at_rest.get((a, b)), hits[(a, b)] / samples,
                         deepest[(a, b)])
        out.pairs.append(rep)
        if rep.rest_depth_mm is not None:
            out.lines.append(f"    {a} - {b}: in contact at rest ({rep.rest_depth_mm:.2f} mm deep): not tested "
                             f"(deepest contact seen {rep.max_depth_mm:.2f} mm)")
            continue
        how = (f"linked by a joint: may touch, rejected beyond {rule.tolerance_mm:g} mm of penetration" if rep.linked
               else "not linked: any contact rejects")
        out.lines.append(f"    {a} - {b}: {how}; rejected in {100 * rep.colliding_fraction:.0f} % "
                         f"(deepest contact {rep.max_depth_mm:.2f} mm)")
        if rep.colliding_fraction > 0.5:
            out.warnings.append(f"parts {a!r} and {b!r} collide in {100 * rep.colliding_fraction:.0f} % of the joint "
                                f"states: synthesis will reject most poses; check their joint frames "
                                f"(`surftrack instruments {where} --figure frames.png`) and limits")
    return out
