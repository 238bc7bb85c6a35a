"""Structured-config schema, registered in Hydra's ConfigStore at import time (so joblib
and submitit workers have it too).  A typo in a key or a wrong type or choice fails at
start with Hydra's message naming the key.  A key Hydra lets in anyway (``+key=value`` adds a
key to a structured node without asking the schema) is refused by ``check_keys`` (InputError
naming the key and the nearest valid one), which the command line and ``compose_config`` run on
every composed config."""

from __future__ import annotations

import dataclasses
import difflib
import logging
import re
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from hairexp.control import REGISTRY as CONTROLLERS
from hairexp.errors import InputError, enum_value
from hairexp.physics.integrators import DEFAULT_INTEGRATOR


class Interpolation(str, Enum):
    cubic = "cubic"
    linear = "linear"


class Derivatives(str, Enum):
    closed_form = "closed_form"   # closed forms, each tested against autograd
    autograd = "autograd"         # batched torch autograd + eigenvalue clamping


class StretchHessian(str, Enum):
    primal_dual = "primal_dual"   # geometric stiffness from a tension iterate (Tournier et al. 2015)
    penalty = "penalty"           # geometric stiffness from the current stretch


class Compile(str, Enum):
    auto = "auto"   # compile the derivative kernels for scenes with >= COMPILE_MIN_VERTICES vertices
    on = "on"
    off = "off"


class OnFailure(str, Enum):
    substep = "substep"   # retry a failed step as two half steps, recursively
    warn = "warn"         # keep a finite non-converged state, flag it in the metrics
    fail = "fail"         # stop the run with an error (exit code 3)


class Builder(str, Enum):
    wisp = "wisp"
    ponytail = "ponytail"
    usd = "usd"              # a USD stage: scene.usd (README "USD scenes")


#: controller.name: the controller registry's names (hairexp/control/__init__.py), so that a new
#: controller needs no edit here.
ControllerName = Enum("ControllerName", {n: n for n in CONTROLLERS}, type=str)


class Targets(str, Enum):
    static = "static"     # t fixed at the rest arc length (TRACKS-style static map)
    sliding = "sliding"   # t is an optimisation variable (paper 3.2, dynamic constraint targets)


class Assignment(str, Enum):
    hard = "hard"   # each strand follows the one guide nearest by eq. (1) (paper 3.1)
    soft = "soft"   # each strand shares itself among the guides near it, weights over tracking.blend_width (paper 5, Fig. 8)


class PointPlacement(str, Enum):
    hair_mass = "hair_mass"     # tracking points at equal shares of the hair mass projected onto the guide
    arc_length = "arc_length"   # equidistant in the guide's arc length (paper 3.1)


class KKTSolve(str, Enum):
    schur = "schur"           # Schur complement on the constraint block (fast)
    reference = "reference"   # plain sparse saddle-point solve (SuperLU)


class SchurSolve(str, Enum):
    exact = "exact"     # S = A H^-1 A^T built at every SQP iteration, solved directly
    krylov = "krylov"   # GMRES preconditioned by the last S built; S rebuilt only when it needs > krylov_max iterations


class GuideInterpolation(str, Enum):
    catmull_rom = "catmull_rom"   # C1 in time between frames (hairexp/guides/animation.py)
    linear = "linear"             # the chord between frames (the velocity jumps at each frame)


class GuideSource(str, Enum):
    rigid = "rigid"     # rest guides carried by the rigid body
    scaled = "scaled"   # rest guides scaled about their roots by keyframed factors, carried by the body
    keyframed = "keyframed"  # guides.keyframes: body-frame poses, cubic in time (hairexp/guides/authoring.py)
    file = "file"       # npz with guide_positions (F, Vg, 3), guide_offsets, fps
    simulated = "simulated"  # the rest guides simulated as free strands (same body, material, gravity)
    usd = "usd"         # the guide prim of the stage scene.usd (scene.usd_guides), one time sample per frame


@dataclass
class MotionConfig:
    """Keyframed rigid motion of the body the roots are attached to."""
    interpolation: Interpolation = Interpolation.cubic
    times: list[float] = field(default_factory=lambda: [0.0])                  # s
    translations: list[list[float]] = field(default_factory=lambda: [[0.0, 0.0, 0.0]])  # m
    rotations_deg: list[list[float]] = field(default_factory=lambda: [[0.0, 0.0, 0.0]])  # rotation vectors, degrees


class ColliderShape(str, Enum):
    sphere = "sphere"
    capsule = "capsule"       # axis along body y, half_length, radius
    box = "box"               # half_extents
    cylinder = "cylinder"     # axis along body y, radius, half_height, spin (rad/s): a wheel
    plane = "plane"           # the half space below body y = 0


@dataclass
class ColliderConfig:
    name: str = "collider"
    shape: ColliderShape = ColliderShape.sphere
    radius: float = 0.1
    half_length: float = 0.1
    half_height: float = 0.05
    half_extents: list[float] = field(default_factory=lambda: [0.1, 0.1, 0.1])
    spin: float = 0.0
    thickness: float = 0.002          # m kept from the surface
    friction: float = 0.3             # Coulomb coefficient
    motion: "MotionConfig" = field(default_factory=lambda: MotionConfig())   # pose keyframes of the collider


@dataclass
class HairConfig:
    """Material of the detail hair (SI)."""
    linear_density: float = 2e-4      # kg/m (a simulated strand stands for a few real hairs)
    stretch_stiffness: float = 20.0   # EA, N
    bending_stiffness: float = 2e-6   # EI, N m^2
    edge_damping: float = 0.0         # N s, damping of stretch rate
    air_drag: float = 0.0             # 1/s, drag against still air


@dataclass
class BodyConfig:
    """The body the roots ride on as a dynamic block on a rail (hairexp/model/dynamic_body.py;
    paper 4, Stylization).  dynamic=false: the keyframed ``scene.motion`` drives it."""
    dynamic: bool = False
    mass: float = 0.01                # kg, the block (the root vertices it carries are added)
    rail_height: float = 0.0          # m, world y of the block's origin when it rests on the rail
    rail_end: float = 0.1             # m, world x where the rail ends (it extends to -x without end)
    rail_friction: float = 0.3        # Coulomb coefficient between block and rail
    velocity: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])   # m/s at t = 0


class RootLayout(str, Enum):
    disk = "disk"   # roots evenly over the root disk (sunflower spiral)
    line = "line"   # roots evenly along the disk's diameter on the first layout axis (body z for hair along -y)


@dataclass
class SceneConfig:
    name: str = "wisp"
    builder: Builder = Builder.wisp
    n_strands: int = 40
    n_vertices: int = 20
    length: float = 0.3               # m
    root_radius: float = 0.02         # m, radius of the disk the roots are spread over
    root_layout: RootLayout = RootLayout.disk   # disk: evenly over it; line: evenly along one diameter (a flat strip)
    root_center: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # m, body frame
    direction: list[float] = field(default_factory=lambda: [0.0, -1.0, 0.0])   # strand direction at rest
    spread: float = 0.0               # rad, random tilt of each strand away from ``direction``
    seed: int = 0
    gravity: list[float] = field(default_factory=lambda: [0.0, -9.81, 0.0])    # m/s^2, Y up
    hair: HairConfig = field(default_factory=HairConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    body: BodyConfig = field(default_factory=BodyConfig)  # dynamic: the block starts at scene.motion's pose (one key)
    colliders: list[ColliderConfig] = field(default_factory=list)
    # s, >= 0: before the run the hair (and simulated guides) settle under gravity for this long,
    # body and colliders held at their t = 0 poses; the run starts, and the tracking registers, on
    # the settled hair at rest (hairexp/physics/settle.py).  0: start from the rest shape as built.
    settle: float = 0.0
    settle_dt: float = 0.04             # s, the settle phase's step (fixed: the same settled state at every run dt)
    # builder usd / guides.source usd: the stage and its prims (README "USD scenes")
    usd: str = ""                       # path of a .usda/.usdc/.usd stage
    usd_body: str = "/Root/Body"        # Xform, transform time-sampled; none: no body prim, scene.motion moves the hair
    usd_hair: str = "/Root/Body/Hair"   # BasisCurves at rest, body space
    usd_guides: str = "/Root/Guides"    # BasisCurves, world space, one time sample per frame
    usd_colliders: str = "/Root/Colliders"  # optional: Sphere, Cube, Cylinder, Capsule, Plane children


class GuideEditKind(str, Enum):
    rotate = "rotate"       # rotate the guide about its root by weight(t) x angle_deg about a body-frame axis
    displace = "displace"   # move vertex at normalised rest arc length s by weight(t) x s^falloff x offset


@dataclass
class GuideEditConfig:
    """One authored edit layered on the guide animation (hairexp/guides/authoring.py)."""
    guide: Optional[int] = None        # index of the edited guide (required: no edit applies to guide 0 unasked)
    kind: GuideEditKind = GuideEditKind.rotate
    times: list[float] = field(default_factory=lambda: [0.0])     # s, strictly increasing keyframes of weight
    weights: list[float] = field(default_factory=lambda: [1.0])   # multiplier of angle_deg / offset (any sign, may exceed 1)
    axis: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])   # rotate: body frame, any length > 0
    angle_deg: float = 0.0             # rotate: degrees at weight 1
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # displace: m, body frame, at the tip at weight 1
    falloff: float = 1.0               # displace: exponent p > 0 of s^p (s = 0 at the root, 1 at the tip)


@dataclass
class GuideKeyframeConfig:
    """A pose of all guides (source=keyframed): count x n_vertices body-frame points, guide by guide."""
    time: float = 0.0                  # s
    points: list[list[float]] = field(default_factory=list)      # m, body frame


@dataclass
class GuidesConfig:
    """The guide animation (see hairexp/guides/animation.py)."""
    source: GuideSource = GuideSource.rigid
    count: int = 1
    n_vertices: int = 8
    layout_radius: float = 0.5         # guide roots on a circle of this fraction of the root radius
    scale_times: list[float] = field(default_factory=lambda: [0.0])   # s (source=scaled)
    scale_factors: list[float] = field(default_factory=lambda: [1.0])
    keyframes: list[GuideKeyframeConfig] = field(default_factory=list)   # source=keyframed
    edits: list[GuideEditConfig] = field(default_factory=list)           # applied in order on top of any source
    collide: bool = False              # source=simulated: the guide simulation collides with scene.colliders
    file: str = ""                     # source=file
    # between frames (a step shorter than a frame, trbdf2's trapezoidal stage): catmull_rom | linear
    interpolation: GuideInterpolation = GuideInterpolation.catmull_rom


@dataclass
class VarianceConfig:
    """Spread control, paper 3.3: P = k_v(t) (V - V_bar(t))^2 per cluster."""
    stiffness: float = 0.0             # k_v in J/m^4; 0 builds no penalty
    times: list[float] = field(default_factory=lambda: [0.0])        # s, keyframes of the two scales
    stiffness_scale: list[float] = field(default_factory=lambda: [1.0])
    target_scale: list[float] = field(default_factory=lambda: [1.0])  # V_bar = rest variance x this
    points: list[int] = field(default_factory=list)                   # tracking-point indices; [] = all


@dataclass
class TrackingConfig:
    targets: Targets = Targets.sliding
    # hard | soft hair-to-guide assignment (hairexp/control/tracking/correspondence.py); soft by
    # default (reports/assignment.md: goaling and celia stop tearing and still hit); splitting,
    # whose guides do mean separate locks, sets hard
    assignment: Assignment = Assignment.soft
    # m, > 0, soft only: a guide whose mean squared distance (eq. 1 / n) to a strand exceeds the
    # nearest guide's by this squared gets e^-1 of its weight
    blend_width: float = 0.0125
    points_per_guide: int = 8
    point_placement: PointPlacement = PointPlacement.hair_mass   # where the points sit on each guide
    kkt: KKTSolve = KKTSolve.schur
    # how kkt=schur treats S = A H^-1 A^T (hairexp/control/tracking/kkt.py SchurKKT): krylov (the
    # reduced system by GMRES to the relative residual and error krylov_tol, preconditioned by the
    # last S built, which is rebuilt when a solve needs more than krylov_max iterations; Celia's
    # tracked step 0.66 x exact's, the same SQP iterations: reports/bench_tracking.md) | exact (S
    # built at every SQP iteration)
    schur: SchurSolve = SchurSolve.krylov
    krylov_tol: float = 1e-6     # (1e-12: the direct solves' residual, round-off; see kkt.KRYLOV_TOL)
    krylov_max: int = 16
    rtol: float = 1e-5                 # |grad_x L| <= atol + rtol * force scale
    atol: float = 1e-10
    ctol_rel: float = 1e-9             # max |C_k| <= ctol_rel * mean hair length
    max_iterations: int = 50
    # the SQP's l1 merit line search measures sufficient decrease from the largest merit of this
    # many last iterates (non-monotone, Grippo et al. 1986; hairexp/control/tracking/sqp.py); 1: monotone
    nonmonotone: int = 5
    # the compressed edges' negative transverse stiffness in the SQP's Hessian once a solve has
    # met its constraints with a full step (hairexp/control/tracking/sqp.py SQPOptions); false
    # (the default, README "Tracking performance"): the PSD stretch Hessian throughout
    exact_compression: bool = False
    # the secant correction of the SQP's Hessian model along its last step where the objective's
    # true curvature there is below half the model's (a buckling wisp; hairexp/control/tracking/
    # sqp.py secant_correction): stylization 13.57 / 170 -> 12.03 / 118 SQP iterations a step
    secant: bool = True
    # elastic mode: a step whose SQP fails while the barrier contact is on (collision.contact=barrier)
    # is solved again with the clusters it could not reach (targets inside an obstacle) relaxed to
    # penalties elastic_stiffness x cluster mass / dt^2 x |C_k|^2 / 2; the others stay exact.
    # metrics.parquet: relaxed_clusters, relaxed_slack_rel_max; summary.json: relaxed_steps, relaxed_slack_rel_max
    elastic: bool = True
    elastic_stiffness: float = 1000.0
    # after the post-solve collision stage moved vertices (collision.contact=stage), the constraints
    # are restored by the smallest mass-weighted move (post-stabilisation), then the colliders'
    # response to it (hairexp/physics/simulator.py _restore; false: left as the stage leaves them)
    restore: bool = True
    max_guide_distance: float = 0.0    # m; > 0: a strand whose RMS distance (eq. 1) to every guide exceeds it is an error
    variance: VarianceConfig = field(default_factory=VarianceConfig)


@dataclass
class ControllerConfig:
    name: ControllerName = ControllerName.free
    attract_stiffness: float = 100.0   # 1/s^2, controller attract: E = 1/2 k m_i |x_i - x_g,i(t)|^2


@dataclass
class SolverConfig:
    dt: float = 0.04                  # s; the frame interval is split into ceil(1/(fps dt)) steps
    rtol: float = 1e-5                # |grad H| <= atol + rtol * force scale
    # a multi-stage scheme's stages before its last (TR-BDF2's trapezoidal or restart stage) are
    # solved to this many times the solver's own rtol (Newton's rtol, the SQP's tracking.rtol), at
    # most 0.1; the last stage (the step's end) to rtol itself; 1: every stage alike (README "Time
    # integrators", "The first stage's tolerance")
    stage_rtol_factor: float = 100.0
    atol: float = 1e-10
    max_iterations: int = 30
    max_backtracks: int = 30
    derivatives: Derivatives = Derivatives.closed_form
    stretch_hessian: StretchHessian = StretchHessian.primal_dual
    compile: Compile = Compile.auto   # torch.compile of the closed forms (first step pays ~10-20 s)
    on_failure: OnFailure = OnFailure.substep
    max_substep_levels: int = 4       # a failing step is split into at most 2^levels substeps
    # a (sub)step at the deepest level that ran out of iterations (Newton's or the SQP's
    # max_iterations, converging but slowly) is tried once more with this many times the
    # iterations before it is kept unconverged; 1: no such attempt (on_failure=substep only)
    last_attempt_iterations: int = 4
    # trbdf2 (the default) | implicit_euler (paper eq. 5) | bdf2 | generalized_alpha (experimental),
    # hairexp/physics/integrators.py.
    # A string, not an Enum, checked by validate_config: an unknown name is an InputError naming
    # solver.integrator (exit 2), and the choices are the integrator registry's keys.
    integrator: str = DEFAULT_INTEGRATOR   # "trbdf2"
    # a step in which the keyed roots' velocity jumps (scene.motion with linear keys) is one
    # implicit Euler step and the integrator restarts after it (hairexp/physics/integrators.py,
    # "Driver discontinuities"); false: the scheme steps through the jump
    restart_at_jumps: bool = True
    # numba: stretch, bending, inertia and gravity by compiled per-strand kernels and a per-strand
    # banded Cholesky (hairexp/physics/strand_kernels.py; other terms stay on torch) | torch: every
    # term through torch and LAPACK's banded solve.  Strings checked by validate_config (InputError).
    kernels: str = "numba"
    # threads of the numba kernels: auto (2 only while the load average leaves a core idle) | 1 | 2
    threads: str = "auto"


class HairHairModel(str, Enum):
    edges = "edges"     # edge-edge contacts: CCD impulses and proximity repulsion (Bridson et al. 2002)
    volume = "volume"   # the hair as a continuum on a grid: friction and pressure (Petrovic et al. 2005, McAdams et al. 2009)


class ContactMode(str, Enum):
    barrier = "barrier"   # hair-object contact inside the objective: IPC barrier + CCD line search + lagged friction
    stage = "stage"       # hair-object contact after the solve (paper 3.4, Bridson et al. 2002) + strain_limit


@dataclass
class CollisionConfig:
    """Contact: hair against the colliders (inside the objective, or after the solve) and hair
    against hair (after the solve: paper 3.4, Bridson et al. 2002)."""
    objects: bool = True              # hair against the scene's colliders (no colliders: nothing runs)
    # barrier: the IPC barrier in the objective Newton and the SQP minimise (hairexp/physics/barrier.py);
    # stage: the post-solve collision stage (hairexp/physics/collisions.py), kept for the ablation.
    # Hair-hair contact (hair_hair) is always the post-solve stage's.
    contact: ContactMode = ContactMode.stage
    barrier_dhat: float = 0.5         # activation distance d_hat as a fraction of max(collider thickness, hair_thickness)
    barrier_stiffness: float = 10.0   # kappa = this x linear density / dt^2 (N/m^2)
    friction: bool = True             # barrier: lagged smoothed Coulomb friction with each collider's coefficient
    friction_epsilon: float = 1e-3    # m/s, barrier friction: slip speeds below this are static friction (IPC eps_v)
    # a step in which a collider sweeps over hair it can reach by more than this fraction of its
    # thinnest half size (sphere/capsule radius, box half extent, cylinder min(radius, half height))
    # is split into equal substeps (fast colliders; 0: never); at most max_travel_substeps of them
    max_travel: float = 0.5
    max_travel_substeps: int = 64
    hair_hair: bool = False           # hair against hair
    hair_thickness: float = 0.001     # m, edge-edge distance kept by repulsion
    skin: float = 0.003               # m, hair-hair neighbour-list skin: the list is reused while no vertex moves skin/2
    max_passes: int = 3
    strain_limit: float = 0.0         # > 0: after object contacts, edge lengths are clamped to (1 -+ this) x rest
    # the post-solve stage also tests edges (not only vertices) against the colliders and pushes
    # out those that dip into one between their vertices (hairexp/physics/collisions.py edge_response)
    edge_response: bool = True
    # stage: the stage's object contacts become penalty planes of a second solve of the step, whose
    # result goes through the stage again (hairexp/physics/contact_planes.py): the hair wraps around
    # the collider in the solve instead of being stretched by the stage's moves (false: the stage's
    # corrections stand, as before 2026-12-07, the ablation with strain_limit)
    resolve: bool = True
    # with resolve: Coulomb friction of resting contact inside the solve (the planes of the vertices
    # the last step's planes pressed, with that normal force, lagged and capped as IPC's; smoothed by
    # friction_epsilon): hair lying on a slope stays where mu > tan(slope) (without it the planes hold
    # hair only normal to the surface and the stage's velocity friction lets it creep down: 40 mm in
    # 1 s on 20 degrees at mu 0.8).  Off by default: it costs SQP iterations on the paper scenes
    # (Celia 5.89 -> 6.16 a step, one step recovered by substeps; README "Contact planes")
    plane_friction: bool = False
    # hair_hair's model: edges (edge-edge contacts) | volume (grid friction and pressure,
    # hairexp/physics/hair_volume.py; linear in the vertices, but strands may pass through each other)
    hair_hair_model: HairHairModel = HairHairModel.edges
    volume_cell: float = 0.01             # m, volume: grid cell size
    volume_friction: float = 2.0          # 1/s, volume: rate at which hair takes the velocity of the hair around it
    volume_pressure_speed: float = 0.1    # m/s, volume: c of the pressure c^2 (rho - rho_0) of over-dense hair


@dataclass
class LoggingConfig:
    rerun: bool = True                # write recording.rrd (rerun is not imported when false)
    progress: bool = True             # progress bar (always quiet when CI is set)
    strict: bool = False              # rerun strict mode: bad shapes become errors


class MeasureName(str, Enum):
    none = "none"
    collider_contact = "collider_contact"   # goaling (wheel), celia (goblet)
    clumps = "clumps"                       # splitting
    tip_variance = "tip_variance"           # spreading
    block_rail = "block_rail"               # stylization
    fan = "fan"                             # fanning


class JudgeName(str, Enum):
    none = "none"
    free_misses_tracked_hits = "free_misses_tracked_hits"
    clumps_match_guides = "clumps_match_guides"
    variance_follows_targets = "variance_follows_targets"
    tracked_leaves_rail = "tracked_leaves_rail"
    hard_clumps_soft_fans = "hard_clumps_soft_fans"


@dataclass
class MeasureConfig:
    """The scene's success measure (hairexp/evaluation/measures.py), written to summary.json."""
    name: MeasureName = MeasureName.none
    collider: str = ""                 # collider_contact: the collider's name
    tolerance: float = 0.002           # m, collider_contact: a hit is within thickness + tolerance
    time: float = -1.0                 # s, clumps: when to cluster (< 0: the last frame)
    threshold: float = 0.02            # m, clumps: single-linkage distance threshold
    strand_fraction: float = 0.5       # clumps: a strand's feature is the mean of its vertices past this fraction
    min_share: float = 0.1             # clumps: smallest clump that counts, as a share of the strands
    # every run: the cohesion summary (summary.json "cohesion", hairexp/evaluation/measures.py)
    cohesion_threshold: float = 0.03   # m: single-linkage distance at which strands' lower parts form one clump
    cohesion_fraction: float = 0.5     # a strand's lower part: its vertices past this fraction
    axis: list[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])   # tip_variance: "ahead" direction
    # tip_variance: the apex is searched from this time (s) up to apex_until (< 0: the last frame)
    apex_from: float = 0.0
    apex_until: float = -1.0
    rail_height: float = 0.0           # m, block_rail
    rail_end: float = 0.0              # m, block_rail


@dataclass
class GuardConfig:
    """The resource guard before a run is built (hairexp/app/guard.py)."""
    # false: a run whose estimated memory exceeds the machine's available memory is refused at start
    # (exit 2, naming the keys that size it); true: it runs anyway, with a warning
    allow_large: bool = False


@dataclass
class VariantConfig:
    """One run of an experiment with a few keys changed (``key=value`` as on the command line)."""
    name: str = "run"
    overrides: list[str] = field(default_factory=list)


class UsdFormat(str, Enum):
    usdc = "usdc"   # result.usdc, binary crate (compact, fast)
    usda = "usda"   # result.usda, ASCII (readable, diffable)


class UsdClips(str, Enum):
    auto = "auto"       # one layer for a run of at most 250 frames (usd_write.CLIP_FRAMES), value clips beyond
    always = "always"   # value clips: result.clips/<k>.usdc hold the per-frame samples, 250 frames each
    never = "never"     # one layer whatever the length (its writer's memory grows with the frames)


class VariantsMode(str, Enum):
    auto = "auto"               # side by side when two cores are idle and the variants are long enough
    parallel = "parallel"       # side by side, one process each, as many at once as usable cores
    sequential = "sequential"   # one after the other in the experiment's process


class OnUnconverged(str, Enum):
    warn = "warn"   # a run with unconverged steps completes (summary converged: false), a warning, exit 0
    fail = "fail"   # such a run fails (status failed, no result files), exit 3


@dataclass
class OutputConfig:
    """The run folder's result files (README "Run folder")."""
    usd_format: UsdFormat = UsdFormat.usdc
    # value clips (README "USD scenes"): the per-frame samples in result.clips/, so that writing a
    # long run's result holds one chunk of frames in memory
    usd_clips: UsdClips = UsdClips.auto


@dataclass
class Config:
    scene: SceneConfig = field(default_factory=SceneConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    collision: CollisionConfig = field(default_factory=CollisionConfig)
    guides: GuidesConfig = field(default_factory=GuidesConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    experiment: Optional[str] = None  # name of the experiment, set by conf/experiment/*.yaml
    measure: MeasureConfig = field(default_factory=MeasureConfig)
    guard: GuardConfig = field(default_factory=GuardConfig)
    variants: list[VariantConfig] = field(default_factory=list)   # [] = one run; else one run per variant
    judge: JudgeName = JudgeName.none  # how the variants' measures decide the experiment's success
    judge_tolerance: float = 0.35      # variance_follows_targets: largest relative miss of a target
    # how an experiment's variants run: auto | parallel | sequential (README "Variants side by side",
    # hairexp/app/variant_processes.py); the results are the same
    variants_mode: VariantsMode = VariantsMode.auto
    frames: Optional[int] = 50        # output frames after the initial one; null: the USD stage's endTimeCode
    fps: Optional[float] = 25.0       # null: the USD stage's timeCodesPerSecond
    output: OutputConfig = field(default_factory=OutputConfig)
    overwrite: bool = False            # true: replace the run in a used run folder (README "Run folder")
    on_unconverged: OnUnconverged = OnUnconverged.warn   # steps that did not converge; none converged: always failed


def require_config(cfg, where: str) -> None:
    """``cfg`` is a composed config with every top-level section, or a named error: the Python
    API's entry points (``assemble``, ``run_folder``) are called with a dict, None or a path, or a
    config with a section deleted (probe of issue 12: an AttributeError deep in validate.py)."""
    from omegaconf import DictConfig

    if not isinstance(cfg, DictConfig):
        raise TypeError(f"{where}: cfg must be a composed config (hairexp.app.compose_config, or Hydra's), "
                        f"got {type(cfg).__name__} {str(cfg)[:60]!r}")
    missing = [f.name for f in dataclasses.fields(Config) if f.name not in cfg]
    if missing:
        raise InputError(f"missing from the config given to {where} (compose it with hairexp.app.compose_config)",
                         ", ".join(missing))
    # a key added under open_dict (cfg.solver.foo = 1) ran and was never refused (independent probe of
    # issue 12, round 35): the command line and compose_config refused it
    check_keys(cfg)


def check_sections(cfg) -> None:
    """InputError for a top-level section deleted on the command line (``~measure``): it said
    "missing from the config given to run_folder (compose it with hairexp.app.compose_config)",
    the Python API's advice (probe of issue 12, round 18)."""
    missing = [f.name for f in dataclasses.fields(Config) if f.name not in cfg]
    if missing:
        raise InputError(f"deleted from the config (~{missing[0]} on the command line); every run reads "
                         f"{'it' if len(missing) == 1 else 'them'}: drop the ~ override", ", ".join(missing))


#: a name that is a folder's name: a variant's, the experiment's (of the default run folders)
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _or_run(name) -> str:
    """The ``or_run`` resolver of conf/config.yaml's default run folders: the experiment's name, or
    ``run`` for a run without one (``oc.select`` keeps a null: ``outputs/None/...``; probe of
    issue 12, round 13).  A name that is not a folder's name is refused: a user's experiment file
    with ``experiment: ../../evil`` wrote its run two folders above outputs/ (independent probe of
    issue 12, round 27)."""
    if name is None or str(name) in ("", "None"):
        return "run"
    if not SAFE_NAME.match(str(name)) or len(str(name).encode()) > 200:
        raise ValueError(f"experiment: {str(name)!r} names the default run folder (outputs/<experiment>/...): use "
                         "letters, digits, _ . - (at most 200 bytes), not starting with . - or _")
    return str(name)


def _share_config_store(self, memo):
    """``ConfigStore.__deepcopy__``: the store itself.  Hydra deep-copies its config repository
    for every composition and for every config group ``--help`` lists (80 times), and the
    repository's structured-config source holds the ConfigStore singleton: each copy was a copy of
    this schema (about 700,000 ``deepcopy`` calls for ``--help``, 6.3 of its 7.2 s under a profiler;
    its wall time 4.7-6.3 -> 3.7-4.2 s; a composition gains about 10 ms).  The source only reads the
    store, and every schema node is stored at import (``register``), so the copies and the singleton
    hold the same configs."""
    return self


def register() -> None:
    if not OmegaConf.has_resolver("or_run"):
        OmegaConf.register_new_resolver("or_run", _or_run)
    if "__deepcopy__" not in vars(ConfigStore):
        ConfigStore.__deepcopy__ = _share_config_store
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="scene", name="base_scene", node=SceneConfig)
    cs.store(group="controller", name="base_controller", node=ControllerConfig)
    cs.store(group="solver", name="base_solver", node=SolverConfig)
    cs.store(group="logging", name="base_logging", node=LoggingConfig)
    cs.store(group="collision", name="base_collision", node=CollisionConfig)


register()


def to_plain(cfg: Any) -> Any:
    """OmegaConf node -> plain Python containers with Enums as their values."""
    from omegaconf import OmegaConf

    def conv(o):
        if isinstance(o, Enum):
            return o.value
        if isinstance(o, dict):
            return {k: conv(v) for k, v in o.items()}
        if isinstance(o, list):
            return [conv(v) for v in o]
        return o

    return conv(OmegaConf.to_container(cfg, resolve=True, enum_to_str=False) if not isinstance(cfg, dict) else cfg)


def _schema_type(node) -> type | None:
    """The dataclass of a structured config node, or None (a plain dict, or not typed)."""
    from omegaconf import OmegaConf

    t = OmegaConf.get_type(node)
    return t if isinstance(t, type) and dataclasses.is_dataclass(t) else None


def _nearest(key: str, valid: list[str]) -> list[str]:
    """The valid names closest to ``key``: close spellings, else names containing it (or it them)."""
    near = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    return near or [v for v in valid if key and (key in v or v in key)][:3]


def unknown_keys(cfg) -> list[tuple[str, list[str], str, list[str]]]:
    """Keys of ``cfg`` that its schema does not have: (dotted key, the nearest valid keys, the
    path of the node that holds it, that node's valid keys), outermost first (a key under an unknown key is not
    listed again).  Records in typed lists (``scene.colliders[i]``, ``guides.edits[i]``,
    ``variants[i]``) are checked against their record type; Hydra's own ``hydra`` node is not
    a schema key.  Interpolations are not resolved."""
    from omegaconf import DictConfig, ListConfig

    found: list[tuple[str, list[str], str, list[str]]] = []

    def walk(node, path: str) -> None:
        if node is None or node._is_none() or node._is_missing() or node._is_interpolation():
            return
        if isinstance(node, ListConfig):
            for i in range(len(node)):
                walk(node._get_node(i), f"{path}[{i}]")
            return
        if not isinstance(node, DictConfig):
            return
        t = _schema_type(node)
        fields = [f.name for f in dataclasses.fields(t)] if t is not None else None
        for key in node.keys():
            key = str(key)
            child_path = f"{path}.{key}" if path else key
            if fields is not None and key not in fields:
                if not (path == "" and key == "hydra"):
                    near = [f"{path}.{f}" if path else f for f in _nearest(key, fields)]
                    found.append((child_path, near, path, fields))
                continue
            walk(node._get_node(key), child_path)

    walk(cfg, "")
    return found


def check_keys(cfg) -> None:
    """InputError naming the first key of ``cfg`` that is not in the schema (a ``+key=value``
    that Hydra added without asking the schema), with the nearest valid key."""
    bad = unknown_keys(cfg)
    if not bad:
        return
    key, near, parent, names = bad[0]
    if near:
        hint = "did you mean " + " or ".join(repr(n) for n in near) + "?"
    else:
        hint = f"the keys of {parent or 'the top level'} are: {', '.join(names)}"
    more = f" (and {len(bad) - 1} more unknown key{'s' if len(bad) > 2 else ''})" if len(bad) > 1 else ""
    raise InputError(f"unknown key, not in the schema (hairexp/app/config.py); {hint}{more}", key)


def unknown_key_hint(key: str) -> str:
    """For a dotted ``key`` that the schema does not have (``solver.rtoll``): "did you mean
    'solver.rtol'?", or the keys of its parent node."""
    import re
    import typing

    parts = re.sub(r"\[\d*\]", "", key.lstrip("+~")).split(".")
    t: Any = Config
    for part in parts[:-1]:
        hints = typing.get_type_hints(t) if isinstance(t, type) and dataclasses.is_dataclass(t) else {}
        if part not in hints:
            return ""
        t = hints[part]
        if typing.get_origin(t) is list:
            t = typing.get_args(t)[0]
    if not (isinstance(t, type) and dataclasses.is_dataclass(t)):
        return ""
    fields = [f.name for f in dataclasses.fields(t)]
    parent = ".".join(parts[:-1])
    near = [f"{parent}.{f}" if parent else f for f in _nearest(parts[-1], fields)]
    if near:
        return "did you mean " + " or ".join(repr(n) for n in near) + "?"
    return f"the keys of {parent or 'the top level'} are: {', '.join(fields)}"


def is_bool_key(key: str) -> bool:
    """Whether the dotted ``key`` (list indices allowed: ``variants[0].x``) is a ``bool`` field of
    the schema."""
    import re
    import typing

    t: Any = Config
    for part in re.sub(r"\[\d*\]", "", key.lstrip("+~")).split("."):
        if not (isinstance(t, type) and dataclasses.is_dataclass(t)):
            return False
        hints = typing.get_type_hints(t)
        if part not in hints:
            return False
        t = hints[part]
        origin = typing.get_origin(t)
        if origin is list:                      # a list of records: its record type
            t = typing.get_args(t)[0]
        elif origin is typing.Union:           # Optional[X]
            t = next((a for a in typing.get_args(t) if a is not type(None)), t)
    return t is bool


def check_bool(key: str, value, text: str | None = None) -> None:
    """InputError naming ``key`` when it is a boolean key of the schema and ``value`` is not a
    boolean (OmegaConf would turn ``2`` or ``"yes"`` into true without a word)."""
    if value is not None and not isinstance(value, bool) and is_bool_key(key):
        raise InputError(f"must be true or false, got {text if text is not None else value}", key.lstrip("+~"))


def check_bool_overrides(overrides) -> None:
    """``check_bool`` for every ``key=value`` of a command line (Hydra's own keys, group
    choices, deletions and sweeps are left to Hydra)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for arg in overrides:
        if arg.startswith("-") or "=" not in arg or arg.lstrip("+~").startswith("hydra"):
            continue
        try:
            o = parser.parse_override(arg)
        except Exception:  # noqa: BLE001  (a syntax error: Hydra's own message)
            continue
        if o.is_delete() or o.is_sweep_override():
            continue
        check_bool(o.key_or_group, o.value(), arg.split("=", 1)[1])


#: the project's Hydra config directory
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def compose_config(overrides: list[str] | tuple[str, ...] = ()):
    """The composed ``config`` with ``overrides`` (``key=value`` strings, as on the command line)
    outside a Hydra app: for scripts, benchmarks and reports.  Hydra's global state is cleared
    before and after, so it can be called any number of times.  A key not in the schema (added
    with ``+``) is an InputError naming it (``check_keys``), as is a boolean key given anything
    but true or false (``check_bool_overrides``: OmegaConf would read ``2`` as true)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if (isinstance(overrides, (str, bytes)) or not isinstance(overrides, (list, tuple))
            or not all(isinstance(o, str) for o in overrides)):
        # a single string was read character by character ("Error parsing override 'e'"; probe of issue 12)
        raise TypeError(f"compose_config: overrides must be a list of 'key=value' strings, got {overrides!r}")
    launch = [o for o in overrides if isinstance(o, str) and o.lstrip("+~").startswith("hydra.")]
    if launch:   # taken without a word (probe of issue 12, round 15)
        logging.getLogger("hairexp").warning(
            "%s not used: compose_config composes hairexp's config only; Hydra's keys are the command line's (the "
            "Python API writes a run into the out_dir given to run or run_folder)", ", ".join(launch))
        overrides = [o for o in overrides if o not in launch]
    check_bool_overrides(overrides)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=list(overrides))
    except Exception as exc:   # Hydra's "use +key" for a key not in the schema, which check_keys refuses too
        unknown = re.match(r"Could not override '([^']+)'\.\s+To append to your config use \+", str(exc))
        bad_value = re.match(r"Error merging override ([^=\s]+)=", str(exc))
        if bad_value and not unknown:   # a value of the wrong type: the key (inside a record: its field) and why
            cause, key = exc.__cause__ or exc, bad_value.group(1)
            field_key = str(getattr(cause, "full_key", None) or "")
            if field_key.startswith(key):
                key = field_key
            elif field_key:   # a field of a record in the value (an edit's kind)
                key = f"{key} (its {field_key})"
            reason = str(cause).split("\n")[0]
            item = re.fullmatch(r"(.+)\[(\d+)\]", field_key)
            if item and "is not a subclass of" in reason and "value: {}" in reason:
                # an index past the list's end: OmegaConf made an empty item (probe of issue 12, round 14)
                raise InputError(f"{item.group(1)} has no item {item.group(2)}: a dotted index sets a key of an item the "
                                 f"list already has; to add items give the whole list ({item.group(1)}=[...], "
                                 "every item to keep)", bad_value.group(1)) from exc
            if (re.fullmatch(r"variants(\[\d+\])?", field_key or key) and
                    ("VariantConfig" in reason or "ListConfig" in reason)):
                # OmegaConf's "str is not a subclass of VariantConfig" (probe of issue 12, round 15)
                given = next((o.split("=", 1)[1] for o in overrides if o.lstrip("+~").split("=", 1)[0] == bad_value.group(1)
                              and "=" in o), "?")
                raise InputError(f"a variant is {{name: <identifier>, overrides: [key=value, ...]}} and variants is a "
                                 "list of them (variants='[{name: a, overrides: [controller.name=tracking]}]', or "
                                 f"variants=[] for the base run alone); got {given}", field_key or key) from exc
            if field_key.rsplit(".", 1)[-1] == "overrides" and key.startswith("variants") and "ListConfig" in reason:
                # a variant's overrides given as one string: OmegaConf's "AnyNode is not a ListConfig" (round 33)
                raise InputError("a variant's overrides are a list of key=value strings, e.g. variants='[{name: a, "
                                 "overrides: [controller.name=free]}]', not a single value",
                                 "variants (its overrides)") from exc
            if "incompatible with type hint 'float'" in reason and "(int)" in reason:   # translations=[[0,0,0]]
                reason += ("; write such a number as a float (0.0, not 0): inside a list of lists OmegaConf does "
                           "not turn an integer into a float")
            elif "incompatible with type hint 'float'" in reason:   # '.nan' in a list of lists (probe, round 13)
                reason += "; a finite number is needed here, written as a float (0.0)"
            raise InputError(reason, key) from exc
        missing = re.search(r"Could not find '([^'/]+)/([^']+)'", str(exc))
        if missing and not unknown:   # Hydra's MissingConfigException, for the Python API too (probe, round 12)
            # the schema's own nodes (base_scene, ...) are not options a user picks (probe of issue 12, round 14)
            options = [o for o in re.findall(r"^\t(\S+)$", str(exc), flags=re.M) if not o.startswith("base_")]
            raise InputError(f"no such option {missing.group(2)!r} of the config group {missing.group(1)}"
                             + (f" (options: {', '.join(options)})" if options else ""), missing.group(1)) from exc
        if type(exc).__name__ == "OverrideParseException" and not unknown:
            # Hydra's multi-line grammar error, for the Python API (probe of issue 12, round 14): the override named
            from hydra.core.override_parser.overrides_parser import OverridesParser

            parser, bad = OverridesParser.create(), None
            for o in overrides:
                try:
                    parser.parse_override(o)
                except Exception:  # noqa: BLE001  (the grammar's errors)
                    bad = o
                    break
            why = [line for line in str(exc).splitlines() if line and not line.startswith(("See ", "Error parsing"))]
            hint = " (an override is key=value)" if bad is not None and "=" not in bad else ""
            raise InputError(f"not a valid override: {(why or ['a syntax error'])[0].strip()}{hint}",
                             bad if bad is not None else "overrides") from exc
        ambiguous = re.match(r"Ambiguous value for argument '([^=']+)=([^']*)'", str(exc))
        if ambiguous and not unknown:   # a sweep's comma list: Hydra's four-line message (probe of issue 16)
            key, value = ambiguous.group(1), ambiguous.group(2)
            raise InputError(f"{value!r} is several values and a run takes one: give one value, a list as {key}=[a,b], "
                             f"a string with commas quoted ({key}='a,b'), or sweep them with -m (python -m hairexp -m "
                             f"{key}={value})", key) from exc
        group = re.search(r"Config group override must be a string or a list. Got (\w+)", str(exc))
        if group and not unknown:   # experiment=null: Hydra's message named no key (probe, round 14)
            key = next((o.split("=", 1)[0].lstrip("+~") for o in overrides if re.fullmatch(r"[+~]{0,2}[\w/]+=(null|~)?", o)),
                       "a config group")
            raise InputError(f"a config group needs an option's name, got {group.group(1)} (leave the key out for no "
                             "experiment)", key) from exc
        if not unknown:
            raise
        key = unknown.group(1)
        inner = re.search(r"Key '([^']+)' not in '(\w+)'", str(exc.__cause__ or exc.__context__ or ""))
        if inner and inner.group(1) not in key.split("."):
            # a key inside a record of the value (a variant's, an edit's, a collider's), named with the
            # record's fields (it said "variants: unknown key ...; did you mean 'variants'?")
            t = globals().get(inner.group(2))
            fields = ", ".join(f.name for f in dataclasses.fields(t)) if dataclasses.is_dataclass(t) else ""
            raise InputError(f"unknown key {inner.group(1)!r} in an item of the value"
                             + (f" (its keys are: {fields})" if fields else ""), key) from exc
        hint = unknown_key_hint(key)
        raise InputError("unknown key, not in the schema (hairexp/app/config.py)" + (f"; {hint}" if hint else ""),
                         key) from exc
    finally:
        GlobalHydra.instance().clear()
    check_keys(cfg)
    check_interpolations(cfg)
    plus = [o for o in overrides if o.startswith("+") and not o.startswith("++") and "=" in o
            and not o.startswith("+hydra")]
    if plus:
        check_plus_overrides(compose_config([o for o in overrides if o not in plus]), plus)
    return cfg


def check_interpolations(cfg) -> None:
    """InputError naming the key whose ``${...}`` cannot be resolved (an unset ``${oc.env:X}``, a
    ``${key}`` not in the config, an unknown resolver): OmegaConf resolves a value only when it
    is read, and such a value ended the run with its traceback, exit 1 (probe of issue 12, round
    11).  Hydra's own node (``hydra.*``) is not looked at."""
    from omegaconf.errors import OmegaConfBaseException

    for key in list(cfg.keys()) if OmegaConf.is_dict(cfg) else []:
        if key == "hydra":
            continue
        try:
            node = cfg[key]
            if OmegaConf.is_config(node):
                OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException as exc:
            where = str(getattr(exc, "full_key", None) or key)
            msg = str(getattr(exc, "msg", None) or exc).split("\n")[0]
            raise InputError(f"cannot resolve its value: {msg}", where) from None


def check_plus_overrides(base, plus: list[str]) -> None:
    """``+key=value`` adds a value where the config has none: refused (InputError naming the key)
    when ``base`` (the config composed without these overrides) already gives ``key`` a value.
    Hydra let ``+scene.colliders=[...]`` replace goaling's wheel without a word, and a user reading
    ``+`` as "add" lost it (probe of issue 12); for a plain key such as ``+solver.dt`` Hydra
    refuses too ("Could not append to config")."""
    for o in plus:
        key = o[1:].split("=", 1)[0]
        try:
            have = OmegaConf.select(base, key, default=None, throw_on_missing=False)
        except Exception:   # noqa: BLE001  (a path OmegaConf cannot select: the composition decides)
            continue
        if have is None or (OmegaConf.is_config(have) and len(have) == 0) or have == "":
            continue
        shown = OmegaConf.to_yaml(have).strip() if OmegaConf.is_config(have) else repr(have)
        if len(shown) > 120:
            shown = shown[:117] + "..."
        raise InputError(f"already has a value in the config ({shown.splitlines()[0] if OmegaConf.is_config(have) else shown}"
                         f"{' ...' if OmegaConf.is_config(have) and len(shown.splitlines()) > 1 else ''}); '+' adds a value where "
                         f"there is none: write {key}=... to replace it (a list: give every item to keep)", key)


def changed_keys(node, default, keys) -> dict:
    """``{key: value}`` of the ``keys`` of ``node`` (a config node) whose value differs from the
    schema's ``default`` (a dataclass instance): the keys a user set.  Values are plain Python
    (lists for sequences, an enum's value)."""
    out = {}
    for key in keys:
        v, d = node[key], getattr(default, key)
        if OmegaConf.is_config(v):   # a record or a list (of records): both sides as plain containers
            v = OmegaConf.to_container(v, enum_to_str=True)
            d = OmegaConf.to_container(OmegaConf.create({"d": d}), enum_to_str=True)["d"]
        else:
            v, d = enum_value(v), list(d) if isinstance(d, (list, tuple)) else enum_value(d)
        if v != d:
            out[key] = v
    return out
