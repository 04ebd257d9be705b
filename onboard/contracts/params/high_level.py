"""Parameters of the high level and of perception (``onboard.high_level``, ``onboard.perception``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal



from onboard.contracts.params.base import Name, Probability, Seed, _Section, above, within


@dataclass(frozen=True)
class PlannerParams(_Section, section="planner"):
    """High-level planner (thesis ch. 6-7, :mod:`onboard.high_level.planning.graph_planner`) and its ``planner`` service.

    Planning model: the CoM double integrator in the horizontal plane, state
    ``[x, y, vx, vy]`` (world frame). Limits are per axis (infinity norm).
    """

    v_max: Annotated[float, above(0.0, 5.0)] = 0.35  # [m/s] planned CoM speed bound in every direction (an octagon: onboard.high_level.planning.bezier_graph.speed_limits); the twin's hopper cruises at 0.25
    a_max: Annotated[float, above(0.0, 20.0)] = 0.5  # [m/s^2] planned CoM acceleration (virtual input) bound per axis
    segment_s: Annotated[float, above(0.0, 60.0)] = 2.0  # [s] duration of one graph edge (a whole number of mpc_dt)
    nodes: Annotated[int, within(1, 1_000_000)] = 5000  # graph nodes over a given planning region; at most this many in an automatic one
    node_density: Annotated[float, above(0.0, 1e4)] = 110.0  # [1/m^2] nodes per square metre of an automatic planning region
    sampling: Literal["uniform", "grid"] = "uniform"  # "uniform" (random positions and velocities) or "grid"
    grid_velocities: Annotated[int, within(1, 15)] = 3  # "grid": velocity values per axis (odd keeps 0)
    rest_grid: Annotated[float, within(0.0, 10.0)] = 0.15  # [m] extra graph nodes at rest on a lattice of this spacing (0: none): narrow gaps
    time_weight: Annotated[float, within(0.0, 10.0)] = 0.15  # [m/s] search cost per second of path on top of its length (0: length only)
    # densification (onboard.high_level.planning.densify): when the search finds no path, nodes at rest are added
    # where it failed, finer level by level, before the planner declares that there is none
    densify_budget_s: Annotated[float, within(0.0, 60.0)] = 0.3  # [s] per plan call (0: never densify); below the reference's 0.5 s staleness
    densify_grid: Annotated[float, above(0.0, 10.0)] = 0.3  # [m] first lattice spacing for a graph without a rest lattice (else half of rest_grid)
    densify_min_grid: Annotated[float, above(0.0, 10.0)] = 0.02  # [m] finest lattice spacing: below it the goal is unreachable "at the finest resolution"
    densify_max_nodes: Annotated[int, within(1, 1_000_000)] = 40_000  # nodes densification may add to one graph (memory, cut time)
    # edges it may add to one graph: what the memory and the cut's time grow with (~0.5 kB an edge with its hull;
    # a resting node among the moving ones gets ~60, and sliding-fast seed 1014 grew a graph by 1.37 M edges)
    densify_max_edges: Annotated[int, within(1, 100_000_000)] = 500_000
    densify_round_nodes: Annotated[int, within(1, 1_000_000)] = 500  # nodes added per round at most (one round, ~0.1-0.3 s on a shared 2-core machine, is what may overrun the budget)
    densify_max_rounds: Annotated[int, within(1, 10_000)] = 4  # rounds per plan call at most when the caller has no clock (lockstep): the same on any machine
    seed: Seed = 0  # node sampling seed
    tube: Annotated[float, within(0.0, 5.0)] = 0.1  # [m] promised low-level tracking tube (CoM position); obstacles grow by it
    tube_growth: Annotated[float, within(1.0, 10.0)] = 1.1  # on a broken promise, plan with the achieved tube times this
    robot_radius: Annotated[float, within(0.0, 2.0)] = 0.0  # [m] robot footprint radius; 0: read from the MJCF
    robot: Name = "indoor"  # MJCF variant: its footprint (unless robot_radius) and the speed it sustains cap v_max
    bounds_padding: Annotated[float, within(0.0, 100.0)] = 0.5  # [m] planning region around start, goal and obstacles (plus twice the margin)
    region_tube: Annotated[float, within(0.0, 5.0)] = 0.2  # [m] the region leaves room for a tube this large: no new graph while the tube grows to it
    bounds_quantum: Annotated[float, above(0.0, 100.0)] = 1.0  # [m] region corners snap to this grid (graph cache hits)
    goal_speed_tol: Annotated[float, within(0.0, 5.0)] = 0.05  # [m/s] graph nodes this slow near the goal may end a path
    start_speed_tol: Annotated[float, within(0.0, 5.0)] = 0.1  # [m/s] velocity part of "the node contains the state"
    replan_hz: Annotated[float, above(0.0, 1000.0)] = 10.0  # [Hz] cut and search when the world or the goal changed
    refine_hz: Annotated[float, above(0.0, 1000.0)] = 100.0  # [Hz] MPC refinement (one SQP iteration per tick)
    mpc_horizon: Annotated[int, within(2, 1000)] = 50  # MPC knots (thesis: 50)
    mpc_dt: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] MPC knot spacing (thesis: 0.1 s)
    mpc_trust: Annotated[float, above(0.0, 100.0)] = 0.5  # [m] trust region of each MPC knot around the graph path (L1)
    halfspaces: Annotated[int, within(0, 64)] = 4  # separating halfspaces per MPC segment (nearest obstacles)
    halfspace_reach: Annotated[float, above(0.0, 100.0)] = 2.0  # [m] obstacles farther than this from a segment are ignored
    replan_deviation: Annotated[float, above(0.0, 100.0)] = 0.3  # [m] replan when the CoM is this far from where the path puts it
    tube_max: Annotated[float, within(0.0, 10.0)] = 0.5  # [m] the tube the planner grows to at most after broken promises
    contract_min_hops: Annotated[int, within(1, 100_000)] = 5  # impacts in the low level's tube window before it is judged
    state_stale_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] an older state estimate is not planned from
    # seen before stepped on (onboard.high_level.planning.seen_space): with a perceived world the robot is committed
    # only to the first commit_s of a reference, and only over ground the camera saw free
    require_seen: bool = True  # false only where no camera watches and no world is given (nothing would ever be seen)
    commit_s: Annotated[float, within(0.0, 10.0)] = 1.0  # [s] beyond a replan (0.1 s) and a stop from cruise (~2 hops)
    commit_step_s: Annotated[float, above(0.0, 1.0)] = 0.05  # [s] reference samples checked along it (one cell at cruise speed)
    heading_lookahead_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] the camera points at where the reference is this far ahead (or a multiple, when that is near)
    heading_min_m: Annotated[float, within(0.0, 10.0)] = 0.15  # [m] nearer than this the heading is left alone (no turning on the spot at the goal)
    # free mode (plans inside perceived free cells only): when no path in them reaches the goal, the
    # path ends at rest near a frontier of the seen space (onboard.high_level.planning.seen_space), the one best by path cost
    # plus frontier_weight times its straight-line distance to the goal; replans move it as the map grows
    frontier_reach: Annotated[float, within(0.0, 10.0)] = 0.3  # [m] a node at rest within the margin plus this of a frontier cell may end such a path
    frontier_min: Annotated[float, within(0.0, 100.0)] = 1.0  # [m] frontier cells nearer the robot are ignored: beside or behind it the camera cannot see them, so standing by them would never resolve them
    frontier_weight: Annotated[float, within(1.0, 100.0)] = 2.0  # [-] cost per metre from a frontier to the goal: at least 1 (the search's heuristic stays admissible), above a known path's cost per metre (1 + time_weight / cruise speed ~ 1.6) so progress toward the goal is worth its path
    frontier_approach_weight: Annotated[float, within(0.0, 1000.0)] = 4.0  # [-] only when the cells reach no frontier (a wall's gap whose cells overlap too thinly for the margin): any node at rest may end the path, at this cost per metre it falls short of that reach over free ground, so the robot goes as near one as they let it, where the cells fitted around it join up (0: it holds)
    frontier_hysteresis: Annotated[float, within(0.0, 100.0)] = 2.0  # [m of cost] the frontier the robot is heading for (nodes within rest_grid of it) is this much cheaper than others: each new view shifts the costs, and two about as good had it turning back and forth between them (maze seed 1 at 0: 50 s; forest 9, 14 and maze 5 at 1: short of the goal when the time ran out, all three reached at 2)
    # obstacles that move (onboard.high_level.planning.moving_obstacles): the cut in time sweeps each along its
    # velocity over when the robot may be near each curve, plus the part of the plan it commits to and the world's age
    obstacle_sweep_s: Annotated[float, within(0.0, 10.0)] = 1.2  # [s] commit_s plus a world period and a replan period
    obstacle_sweep_max_m: Annotated[float, within(0.0, 10.0)] = 1.0  # [m] a sweep is at most this long (a kick stops)
    obstacle_band_m: Annotated[float, above(0.0, 100.0)] = 0.5  # [m] curves this wide a band of distance from the robot share one time window


@dataclass(frozen=True)
class PerceptionParams(_Section, section="perception"):
    """Depth image -> occupancy grid -> convex sets (:mod:`onboard.perception`), ``perception`` service.

    Thesis 3100-3116 (Algorithm 4, convex free cells or convex obstacles) and 3336 (the
    outdoor pipeline: depth at apex, segmentation, vertical binning, Algorithm 4).
    Lengths [m], angles [deg], times [s]; cell counts in grid cells.
    """

    # service
    rate_hz: Annotated[float, above(0.0, 100.0)] = 5.0  # polytope publication rate (issue: 4-20 Hz; the published node ran at 5)
    mode: Literal["free", "obstacles"] = "obstacles"  # "free": convex free cells; "obstacles": convex obstacles
    # point cloud
    pixel_stride: Annotated[int, within(1, 64)] = 1  # use every n-th pixel in both directions
    max_range_m: Annotated[float, above(0.0, 100.0)] = 6.0  # farther returns are dropped (depth noise grows with range^2)
    # geometric segmentation: RANSAC ground plane, height and slope thresholds
    ransac_iterations: Annotated[int, within(1, 10_000)] = 64
    ransac_inlier_m: Annotated[float, above(0.0, 1.0)] = 0.03  # plane distance of a RANSAC inlier
    ground_min_points: Annotated[int, within(3, 1_000_000)] = 30  # fewer inliers: fall back to the plane z = 0
    ground_tilt_max_deg: Annotated[float, within(0.0, 90.0)] = 25.0  # a ground-plane candidate tilted more is rejected
    plane_keep_fraction: Probability = 0.9  # keep the last plane while it has this share of a new fit's inliers
    ground_tol_m: Annotated[float, within(0.0, 1.0)] = 0.04  # points this close to the ground plane are ground...
    ground_tol_per_m: Annotated[float, within(0.0, 1.0)] = 0.012  # ...plus this per metre of range (depth noise grows with range)
    slope_max_deg: Annotated[float, within(0.0, 90.0)] = 25.0  # ground points whose surface is steeper are obstacles
    obstacle_height_max_m: Annotated[float, above(0.0, 100.0)] = 1.0  # points higher above the ground are ignored (overhangs)
    depth_jump_m: Annotated[float, above(0.0, 10.0)] = 0.10  # neighbours farther apart than this (per pixel) give no surface normal
    normal_step_px: Annotated[int, within(1, 64)] = 2  # surface normals from neighbours this many pixels away (noise vs detail)
    seed: Seed = 0  # RANSAC and K-means randomness
    # occupancy grid: world frame, square, follows the robot by whole cells
    grid_cells: Annotated[int, within(2, 4096)] = 200  # the published pipeline: 200 x 200 cells of 5 cm
    resolution_m: Annotated[float, above(0.0, 10.0)] = 0.05
    min_points_per_cell: Annotated[int, within(1, 100_000)] = 2  # obstacle points a cell needs in one view to count as hit
    hit_evidence: Annotated[float, within(0.0, 100.0)] = 1.0  # added per view to a hit cell
    miss_evidence: Annotated[float, within(0.0, 100.0)] = 0.5  # removed per view from a cell seen as ground
    evidence_max: Annotated[float, above(0.0, 1000.0)] = 3.0  # saturation, both signs
    occupied_threshold: Annotated[float, within(0.0, 1000.0)] = 0.9  # evidence at or above: occupied
    free_threshold: Annotated[float, within(0.0, 1000.0)] = 0.4  # evidence at or below minus this: free
    decay_half_life_s: Annotated[float, above(0.0, 86_400.0)] = 10.0  # evidence of cells not seen in a view fades to unknown
    carve_range_m: Annotated[float, within(0.0, 100.0)] = 4.0  # ground seen along a ray up to this range is free
    footprint_radius_m: Annotated[float, within(0.0, 10.0)] = 0.15  # the robot stands here: free
    # free mode only: the ground around where the robot stands or stood is free, out to this radius, where in
    # sight of it past nothing seen occupied. The camera never sees it: ground within ~0.35 m ahead (its near
    # blind zone) and beside the robot. Twice the planner's margin (robot radius 0.13 + tube 0.1): the
    # corridor between the unseen ground beside the robot, from it to what the camera saw ahead, must be
    # wider than the margin on both sides for a plan to leave through it
    stand_radius_m: Annotated[float, within(0.0, 10.0)] = 0.5
    recenter_distance_m: Annotated[float, above(0.0, 1000.0)] = 2.0  # re-centre the grid when the robot is this far off centre
    # convex free cells (Algorithm 4)
    cluster_cells: Annotated[int, within(1, 10_000_000)] = 2500  # free cells per K-means cluster (sets k)
    clusters_min: Annotated[int, within(1, 1000)] = 2
    clusters_max: Annotated[int, within(1, 1000)] = 24
    ellipse_sigmas: Annotated[float, above(0.0, 10.0)] = 3.0  # thesis: three standard deviations
    kmeans_max_points: Annotated[int, within(1, 10_000_000)] = 4000  # K-means runs on blocks of cells, about this many
    coverage_rounds: Annotated[int, within(0, 100)] = 3  # refits of the free cells the polygons missed
    coverage_target: Probability = 0.95  # no more coverage rounds once reached
    residual_min_cells: Annotated[int, within(1, 10_000_000)] = 12  # missed pieces smaller than this are left alone
    repair_rounds: Annotated[int, within(0, 100)] = 2  # connectivity repairs between groups of polygons
    repair_radius_cells: Annotated[float, above(0.0, 1000.0)] = 6.0  # circle metric of repair and must-cover fits
    # free mode: the robot gets cells of its own, fitted around it, so that plans can leave it: one in a circle
    # (it stands as deep in it as its clearance allows) and, seen through the gap between its blind sides,
    # corridors along ellipses of start_fit_aspect in start_fit_directions directions over a half turn
    start_fit_radius_m: Annotated[float, within(0.0, 100.0)] = 2.0  # [m] the circle's radius and the ellipses' long half axis (0: no own cells)
    start_fit_directions: Annotated[int, within(0, 64)] = 4  # ellipses, their long axes evenly spread over 180 deg
    start_fit_aspect: Annotated[float, within(1.0, 100.0)] = 4.0  # long over short half axis: faces near the robot's sides run along the axis
    # convex obstacles
    obstacle_method: Literal["hull", "rect"] = "hull"  # "hull" or "rect" (minimum-area rectangle, as the thesis)
    obstacle_solidity_min: Probability = 0.6  # cells / hull area below which a blob is split
    obstacle_split_min_cells: Annotated[int, within(1, 10_000_000)] = 8
    obstacle_slack_m2: Annotated[float, within(0.0, 1e6)] = 0.1  # [m^2] of its hull a blob may leave empty before it is split
    obstacle_split_depth: Annotated[int, within(0, 64)] = 10  # halvings per blob at most
    obstacles_max: Annotated[int, within(1, 100_000)] = 400  # splits over all blobs, the largest first
    # terrain segmentation from colour and depth (onboard/perception/terrain.py, thesis 8.2): outdoors
    segmenter: Literal["geometric", "color"] = "geometric"  # "color": the D435's aligned colour image too
    terrain_clusters: Annotated[int, within(2, 32)] = 6  # K-means colour clusters (CIE Lab) per image
    terrain_seed_range_m: Annotated[float, above(0.0, 10.0)] = 1.2  # [m] ground this near the foot seeds the colour
    terrain_seed_share: Probability = 0.2  # a cluster holding this share of the seed pixels is traversable colour
    terrain_color_distance: Annotated[float, above(0.0, 1000.0)] = 14.0  # Lab distance of a cluster centre from the seed's colour
    # weight of Lab's lightness in terrain_color_distance: a surface's texture and the auto exposure move its
    # lightness, a material change moves its hue (paving to grass). With the full L the forest floor's darker
    # texture cluster read as another surface (terrain_eval IoU, seeds 40-47: forest 0.908 -> 0.962 at 0.25,
    # sidewalk 0.952 -> 0.964)
    terrain_lightness_weight: Annotated[float, within(0.0, 1.0)] = 0.25
    terrain_blur_px: Annotated[int, within(1, 31)] = 5  # odd: smoothing before clustering (texture is not class)
    terrain_min_seed_px: Annotated[int, within(1, 1_000_000)] = 40  # fewer seed pixels: the last view's colours stand
    terrain_memory: Probability = 0.7  # weight of the last views' seed colour against this view's
    # once terrain_seed_confirm views in a row agreed with it, a view's seed this far (Lab) from the remembered
    # colour is a view across a boundary (the robot at a walkway's end facing the grass: the nearest ground
    # in view is not what it stands on), not a new surface underfoot: it neither moves the memory nor makes
    # its clusters traversable. Paving to grass is ~58 (the sidewalk's colours); at 30 the twin's exposure
    # changes alone tripped it. Before that (a first view across a boundary), the memory follows the views
    terrain_seed_jump: Annotated[float, above(0.0, 1000.0)] = 45.0
    terrain_seed_confirm: Annotated[int, within(1, 1000)] = 5

    def _relations(self) -> list[str]:
        if self.clusters_min > self.clusters_max:
            return [f"perception.clusters_min: above clusters_max ({self.clusters_min} > {self.clusters_max})"]
        return []
