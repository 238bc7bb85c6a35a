"""Whether an experiment met the artistic intent, from its variants' measures.

Each judge takes ``{variant name: measures dict}`` plus the variants' configs and returns
``(success, details)``.  The rules are the issue's statements of each scene's intent:

* ``free_misses_tracked_hits`` (goaling, celia): the free run does not hit the collider and
  every tracked run does.
* ``clumps_match_guides`` (splitting): the free run makes one clump; a tracked run with k
  guides makes k clumps.
* ``variance_follows_targets`` (spreading): over the tracked runs sorted by target, the tip
  variance at the apex rises monotonically, and each lands within ``judge_tolerance``
  (relative) of its target (the cluster variance ratio against the target ratio).
* ``tracked_leaves_rail`` (stylization): the free run leaves the block on the rail, the tracked
  run pulls it off.

* ``hard_clumps_soft_fans`` (fanning, paper Fig. 8): every hard-assigned tracked run splits
  the hair into separate clumps (>= 2 at ``measure.threshold``); every soft-assigned one fans
  out (no gap between neighbouring strands across the spread wider than ``FAN_GAP_RATIO`` x
  the mean spacing, in any frame) and still tracks (largest residual <= ``FAN_RESIDUAL`` x
  the hair length).  The free run is reported, not judged.

``RUN_RULES`` holds each judge's per-run rule (the test one run meets or not), which the judges
apply to their variants and experiments/baselines.py to every controller's run.
"""

from __future__ import annotations


# -- the per-run rules: what one run must show, the half of each judge that a tracked run meets --
# Each takes the run's measures m, its facts (``controller``, ``guides``, ``target_scale``: the
# variant facts of hairexp/app/experiment.py) and the judge's tolerance, and returns (met, a
# sentence of the figures).  The judges below apply them to their tracked variants;
# experiments/baselines.py applies them to every controller's run.
def hits_collider(m: dict, facts: dict, tol: float) -> tuple[bool, str]:
    """The hair touches the collider (measure ``collider_contact`` ``hit``)."""
    return bool(m["hit"]), f"min distance {m['min_distance']:+.4f} m, {m['contacts']} contacts"


def clumps_equal_guides(m: dict, facts: dict, tol: float) -> tuple[bool, str]:
    """As many clumps (measure ``clumps``) as guides (``guides.count``)."""
    want = int(facts["guides"])
    return m["clumps"] == want, f"{m['clumps']} clumps {m.get('clump_sizes')} (want {want})"


def variance_on_target(m: dict, facts: dict, tol: float) -> tuple[bool, str]:
    """The cluster variance ratio at the apex within ``tol`` (relative) of its target ratio."""
    r, t = m["cluster_variance_ratio"], m["cluster_target_ratio"]
    err = abs(r / t - 1.0)
    return bool(err <= tol), f"V/V_rest {r:.2f} vs target {t:.2f} (error {100 * err:.0f} %)"


def leaves_rail(m: dict, facts: dict, tol: float) -> tuple[bool, str]:
    """The block leaves the rail (measure ``block_rail`` ``left_rail``)."""
    return bool(m["left_rail"]), f"travel {m['travel']:.3f} m"


#: fanning: the widest gap a fanned-out wisp may have, in mean spacings, and its largest residual / hair length
FAN_GAP_RATIO, FAN_RESIDUAL = 2.0, 1e-6


def fans_or_clumps(m: dict, facts: dict, tol: float) -> tuple[bool, str]:
    """Soft assignment: the hair fans out (``gap_ratio_max`` <= FAN_GAP_RATIO) and tracks
    (``residual_rel_max`` <= FAN_RESIDUAL); hard: it splits into >= 2 clumps."""
    figures = (f"{m['clumps']} clumps, widest gap {m['gap_ratio_max']:.2f} x the mean spacing, "
               f"residual {m['residual_rel_max']} x L")
    if facts.get("assignment") == "soft":
        r = m["residual_rel_max"]
        return bool(m["gap_ratio_max"] <= FAN_GAP_RATIO and r is not None and r <= FAN_RESIDUAL), figures
    return bool(m["clumps"] >= 2), figures


#: judge name -> its per-run rule (what a tracked run of the scene must show)
RUN_RULES = {"free_misses_tracked_hits": hits_collider, "clumps_match_guides": clumps_equal_guides,
             "variance_follows_targets": variance_on_target, "tracked_leaves_rail": leaves_rail,
             "hard_clumps_soft_fans": fans_or_clumps}


#: judge name -> the measure (``measure.name``) its rule reads
JUDGE_MEASURES = {"free_misses_tracked_hits": "collider_contact", "clumps_match_guides": "clumps",
                  "variance_follows_targets": "tip_variance", "tracked_leaves_rail": "block_rail",
                  "hard_clumps_soft_fans": "fan"}


#: judge name -> the controllers its variants must include (a judge that compares free with
#: tracked runs has no verdict without both; checked before any variant runs, hairexp/app/experiment.py)
JUDGE_NEEDS = {"free_misses_tracked_hits": ("free", "tracking"), "clumps_match_guides": (),
               "variance_follows_targets": ("tracking",), "tracked_leaves_rail": ("free", "tracking"),
               "hard_clumps_soft_fans": ("tracking",)}


def missing_controllers(judge: str, controllers) -> list[str]:
    """The controllers ``judge`` needs that none of the variants (``controllers``) has."""
    have = set(controllers)
    return [c for c in JUDGE_NEEDS.get(judge, ()) if c not in have]


def _met(rule, m: dict, facts: dict, tol: float = 0.0) -> bool:
    return rule(m, facts, tol)[0]


# -- the judges: the variants together ------------------------------------------------------
def _free_fails_tracked_meets(rule, m: dict, variants: dict) -> bool:
    """There are free and tracked variants; no free one meets ``rule`` and every tracked one does."""
    free = [k for k in m if variants[k]["controller"] == "free"]
    tracked = [k for k in m if variants[k]["controller"] == "tracking"]
    return bool(free and tracked and all(not _met(rule, m[k], variants[k]) for k in free)
                and all(_met(rule, m[k], variants[k]) for k in tracked))


def free_misses_tracked_hits(m: dict, variants: dict, tol: float):
    ok = _free_fails_tracked_meets(hits_collider, m, variants)
    return ok, {k: {"hit": m[k]["hit"], "min_distance": m[k]["min_distance"]} for k in m}


def clumps_match_guides(m: dict, variants: dict, tol: float):
    details, ok = {}, True
    for k, v in m.items():
        facts = {**variants[k], "guides": 1} if variants[k]["controller"] == "free" else variants[k]  # free: one clump
        details[k] = {"clumps": v["clumps"], "expected": facts["guides"]}
        ok &= _met(clumps_equal_guides, v, facts)
    return bool(ok), details


def variance_follows_targets(m: dict, variants: dict, tol: float):
    tracked = sorted((variants[k]["target_scale"], k) for k in m if variants[k]["controller"] == "tracking")
    ratios = [m[k]["cluster_variance_ratio"] for _, k in tracked]
    targets = [m[k]["cluster_target_ratio"] for _, k in tracked]
    monotone = all(b > a for a, b in zip(ratios, ratios[1:]))
    errors = [abs(r / t - 1.0) for r, t in zip(ratios, targets)]
    ok = bool(tracked) and monotone and all(_met(variance_on_target, m[k], variants[k], tol) for _, k in tracked)
    return ok, {"monotone": monotone, "targets": targets, "ratios": ratios, "relative_errors": errors,
                "tip_variance_ratios": {k: m[k]["tip_variance_ratio"] for k in m}, "tolerance": tol}


def tracked_leaves_rail(m: dict, variants: dict, tol: float):
    ok = _free_fails_tracked_meets(leaves_rail, m, variants)
    return ok, {k: {"left_rail": m[k]["left_rail"], "travel": m[k]["travel"]} for k in m}


def hard_clumps_soft_fans(m: dict, variants: dict, tol: float):
    tracked = [k for k in m if variants[k]["controller"] == "tracking"]
    details = {k: fans_or_clumps(m[k], variants[k], tol)[1] for k in m}
    ok = bool(tracked) and all(_met(fans_or_clumps, m[k], variants[k]) for k in tracked)
    return ok, {"runs": details, "gap_ratio_limit": FAN_GAP_RATIO, "residual_limit": FAN_RESIDUAL}


JUDGES = {"free_misses_tracked_hits": free_misses_tracked_hits, "clumps_match_guides": clumps_match_guides,
          "variance_follows_targets": variance_follows_targets, "tracked_leaves_rail": tracked_leaves_rail,
          "hard_clumps_soft_fans": hard_clumps_soft_fans}
