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
"""

from __future__ import annotations


def free_misses_tracked_hits(m: dict, variants: dict, tol: float):
    free = [k for k in m if variants[k]["controller"] == "free"]
    tracked = [k for k in m if variants[k]["controller"] == "tracking"]
    ok = bool(free and tracked and all(not m[k]["hit"] for k in free) and all(m[k]["hit"] for k in tracked))
    return ok, {k: {"hit": m[k]["hit"], "min_distance": m[k]["min_distance"]} for k in m}


def clumps_match_guides(m: dict, variants: dict, tol: float):
    details, ok = {}, True
    for k, v in m.items():
        want = 1 if variants[k]["controller"] == "free" else variants[k]["guides"]
        details[k] = {"clumps": v["clumps"], "expected": want}
        ok &= v["clumps"] == want
    return bool(ok), details


def variance_follows_targets(m: dict, variants: dict, tol: float):
    tracked = sorted((variants[k]["target_scale"], k) for k in m if variants[k]["controller"] == "tracking")
    ratios = [m[k]["cluster_variance_ratio"] for _, k in tracked]
    targets = [m[k]["cluster_target_ratio"] for _, k in tracked]
    monotone = all(b > a for a, b in zip(ratios, ratios[1:]))
    errors = [abs(r / t - 1.0) for r, t in zip(ratios, targets)]
    ok = bool(tracked) and monotone and max(errors) <= tol
    return ok, {"monotone": monotone, "targets": targets, "ratios": ratios, "relative_errors": errors,
                "tip_variance_ratios": {k: m[k]["tip_variance_ratio"] for k in m}, "tolerance": tol}


def tracked_leaves_rail(m: dict, variants: dict, tol: float):
    free = [k for k in m if variants[k]["controller"] == "free"]
    tracked = [k for k in m if variants[k]["controller"] == "tracking"]
    ok = bool(free and tracked and all(not m[k]["left_rail"] for k in free) and all(m[k]["left_rail"] for k in tracked))
    return ok, {k: {"left_rail": m[k]["left_rail"], "travel": m[k]["travel"]} for k in m}


JUDGES = {"free_misses_tracked_hits": free_misses_tracked_hits, "clumps_match_guides": clumps_match_guides,
          "variance_follows_targets": variance_follows_targets, "tracked_leaves_rail": tracked_leaves_rail}
