"""vbnav goto: drive to a pose in the VSLAM's reference frame."""
from __future__ import annotations

import math
import sys

from vbnav.control.commands._common import add_config_arg, finite, positive, refuse_unserved_live_view
from vbnav.control.commands._net import add_telemetry_args, attach_telemetry
from vbnav.control.map_planning import (goal_moved_note, grid_params, localise_problem, localise_start,
                                        map_route_in_reference_frame, no_path_reason, plan_path, sim_start_problem,
                                        stop_approach)

ROBOT_RADIUS_M = 0.2    # --robot-radius when not given (it defaults to None: without --map it is refused)


def register(sub) -> None:
    p = sub.add_parser(
        "goto", help="drive to a goal pose using the VSLAM",
        description="Drive the robot to a goal pose given in the VSLAM's reference frame: the robot's pose when "
                    "the command starts (x to the right, z forward, metres; theta in degrees, positive turning "
                    "right). The VSLAM (section 11.3) localises the robot, odometry bridges between frames, and a "
                    "polar-coordinate control law drives forward to the goal, slowing near it, then turns on the "
                    "spot to the goal heading. Metric scale comes from a stereo camera (the default "
                    "configs/sim_stereo.yaml on the simulated robot, which starts at its sim.start_pose in the "
                    "simulated room) or, with 'vslam: {metric_scale: odometry}' in the configuration, from the "
                    "wheels for a single camera (the robot first creeps ahead, up to vslam.goto.blind_distance_m, "
                    "0.3 m by default, to initialise). Exit code 0 when the goal is reached, 1 when not (duration, "
                    "lost).")
    add_config_arg(p, default="sim_stereo")
    p.add_argument("--goal", required=True, nargs=3, type=finite, metavar=("X", "Z", "THETA_DEG"),
                   help="goal pose in the reference frame: x (m, right), z (m, forward), heading (degrees)")
    p.add_argument("--map", metavar="MAP",
                   help="a line map (vbnav map build): the goal is then in the map's frame, and the robot plans a "
                        "path around the mapped walls and objects (A* on a grid grown by the robot radius) to a goal "
                        "it may have only seen; the obstacle stop stays in force")
    p.add_argument("--start", nargs=3, type=finite, default=None, metavar=("X", "Z", "THETA_DEG"),
                   help="with --map: the robot's pose in the map's frame at the start (default 0 0 0: where the "
                        "mapping drive started)")
    p.add_argument("--localise", action="store_true",
                   help="with --map: find the start pose against the map from the first stereo frame, searched "
                        "0.3 m / 12 deg around --start; exit 1 when the map does not confirm a pose there")
    p.add_argument("--static-map", action="store_true",
                   help="with --map: plan once from the map file; by default a stereo robot keeps mapping while it "
                        "drives and plans again when the grown map blocks the route ahead")
    p.add_argument("--map-out", metavar="FILE",
                   help="with --map: write the map as it grew while driving to FILE at the end (atomically)")
    add_telemetry_args(p, overwrite_help="an existing --map-out map")
    p.add_argument("--robot-radius", type=positive, default=None, metavar="M",
                   help=f"with --map: the robot's radius for planning, m (default robot.footprint_radius, or "
                        f"{ROBOT_RADIUS_M} without it)")
    p.add_argument("--duration", type=positive, default=120.0, metavar="S",
                   help="give up after S seconds (default 120; simulated seconds on the simulated clock)")
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.finishing import finishing
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.runtime.runtime import DEVICE_FAULTS, Runtime
    from vbnav.control.controllers.goto import GotoController
    from vbnav.control.stages.vslam import make_vslam_stage, stereo_baseline_of
    from vbnav.vision.geometry import Pose2

    cfg = load_config(args.config)
    refuse_unserved_live_view(cfg, args.no_telemetry)
    nav = cfg.vslam
    if nav.metric_scale == "stereo" and stereo_baseline_of(cfg) is None and cfg.camera.driver == "sim":
        print(f"vbnav goto: {cfg.source}: camera.options.stereo_baseline is not set; the VSLAM needs the stereo "
              "pair for metric scale (try --config sim_stereo, or set vslam.metric_scale: odometry for a single "
              "camera scaled by the wheels)", file=sys.stderr)
        return 2
    goal = Pose2(args.goal[0], args.goal[1], math.radians(args.goal[2]))
    waypoints = None
    map_only = [o for o, given in (("--start", args.start is not None), ("--localise", args.localise),
                                   ("--static-map", args.static_map), ("--map-out", args.map_out),
                                   ("--robot-radius", args.robot_radius is not None)) if given]
    if map_only and not args.map:
        print(f"vbnav goto: {', '.join(map_only)} need(s) --map (they place the robot in the map's frame, plan on "
              "the map or act on it)", file=sys.stderr)
        return 2
    if args.map_out and args.static_map:
        print("vbnav goto: --map-out needs the map to grow while driving (leave out --static-map)", file=sys.stderr)
        return 2
    if args.localise:
        problem = localise_problem(cfg)
        if problem:        # before any device opens
            print(f"vbnav goto: --localise: {problem}", file=sys.stderr)
            return 2
    radius = next(r for r in (args.robot_radius, cfg.robot.footprint_radius, ROBOT_RADIUS_M) if r is not None)
    if args.overwrite and not args.map_out and not args.record:
        print("vbnav goto: --overwrite replaces an existing --map-out or --record file; without --map-out or "
              "--record it has nothing to replace", file=sys.stderr)
        return 2
    from vbnav.control.commands._common import apart_from_config, distinct_files, output_file, record_target_error
    output_file(args.record, "--record")
    if args.map_out:
        from vbnav.control.commands._common import not_recorded_yet
        output_file(args.map_out, "--map-out")
        distinct_files({"--map-out": args.map_out, "--record": args.record})
        not_recorded_yet([args.map_out], f"--map-out {args.map_out}", args.overwrite, "a map is")
    apart_from_config(cfg, {"--map-out": args.map_out, "--record": args.record})
    why = record_target_error(args)
    if why:
        print(f"vbnav goto: {why}", file=sys.stderr)
        return 2
    try:
        stage = make_vslam_stage(cfg)
    except ValueError as exc:
        print(f"vbnav goto: {cfg.source}: {exc}", file=sys.stderr)
        return 2
    stages = [stage]
    live = None
    start = Pose2(*args.start[:2], math.radians(args.start[2])) if args.start else Pose2()
    if args.map:       # a bad map file is refused before any device opens
        from vbnav.control.line_map_file import load_map
        from vbnav.control.live_map import LiveMap
        lmap, meta = load_map(args.map)
        wrong = "" if args.localise else sim_start_problem(cfg, meta, args.map, start)
        if wrong:
            print(f"vbnav goto: {wrong}", file=sys.stderr)
            return 2
        if not args.static_map:
            live, why = LiveMap.for_goto(cfg, lmap, meta, stage, lambda: start)
            if live is None:
                print(f"vbnav goto: the map is not updated while driving ({why}); planning once from {args.map}")
                if args.map_out:
                    print(f"vbnav goto: --map-out: {why}", file=sys.stderr)
                    return 2
            else:
                stages.append(live.stage)
    robot = make_robot(cfg, stages)
    if args.map:
        if args.localise:
            found, say = localise_start(cfg, robot.camera, lmap, args.map, start)
            if found is None:               # not localised at all (no frame): the guess is not what failed
                print(f"vbnav goto: --localise: {say}", file=sys.stderr)
                robot.drive.close()
                return 1
            if not found.ok:
                print(f"vbnav goto: the map does not confirm a start pose within 0.3 m / 12 deg of "
                      f"({start.x:+.2f}, {start.z:+.2f}, {math.degrees(start.theta):+.1f} deg): {say}; give --start "
                      f"nearer the robot's pose, or turn it toward a mapped view", file=sys.stderr)
                robot.drive.close()         # never enabled: released as it was opened
                return 1
            start = found.pose
            print(f"localised against the map: x={start.x:+.3f} z={start.z:+.3f} "
                  f"theta={math.degrees(start.theta):+.2f} deg ({say})")
        try:
            planned = plan_path(lmap, meta, start, goal, radius, stop_approach(cfg))
        except ValueError as exc:           # the grid over the map, --start and --goal would not fit in memory
            print(f"vbnav goto: {args.map}: --start ({start.x:+.2f}, {start.z:+.2f}), --goal ({goal.x:+.2f}, "
                  f"{goal.z:+.2f}): {exc}; give a goal within reach of the map", file=sys.stderr)
            robot.drive.close()
            return 2
        if planned is None:
            print(f"vbnav goto: {args.map}: {no_path_reason(lmap, meta, start, goal, radius)}", file=sys.stderr)
            robot.drive.close()
            return 1
        print("planned path (map frame): " + " -> ".join(f"({x:+.2f}, {z:+.2f})" for x, z in planned))
        moved = math.hypot(planned[-1][0] - goal.x, planned[-1][1] - goal.z)
        if moved > 0.0:
            margin = f"{radius + grid_params(radius).clearance_m:.2f} m (--robot-radius + clearance) of a mapped wall or object"
            print(f"goto: {goal_moved_note(goal, moved, margin, 'the --goal')}")
        goal_map = goal
        waypoints, end = map_route_in_reference_frame(planned, start, goal)
        goal = start.between(goal)          # reported against the goal as given; driven to the path's end
    controller = GotoController(end if args.map else goal, nav.goto, cfg.robot.max_linear_speed, cfg.robot.max_angular_speed,
                                waypoints=waypoints, follow_route=bool(args.map))
    rt = Runtime(cfg, robot.drive, controller, robot.clock, robot.pipeline)
    link = attach_telemetry(rt, cfg, args)     # state, network commands and the live view; --record
    if link is None:
        robot.drive.close()         # never enabled: released as it was opened
        return 3
    if live is not None:                # on a simulated clock the slow loops run inline, on simulated time
        live.attach(controller, robot.clock.simulated, start, goal_map, radius, moved or None, stop_approach(cfg),
                    next((s for s in robot.pipeline.stages if s.kind == "obstacles"), None))
    printer = ProgressPrinter()
    # With --map on the simulator, the ground truth's nearest approach to a wall or box is sampled at 20 Hz.
    world = robot.world if args.map else None
    every_s = 0.05 if world is not None else 1.0
    closest = [math.inf]
    ticks = [0]
    # Poses are said in the frame the goal was given in: the map's with --map (the controller's is the start's).
    in_goal_frame = start.compose if args.map else (lambda p: p)
    frame = " (map frame)" if args.map else ""

    def estimate(s: dict) -> Pose2:
        return in_goal_frame(Pose2(s["x"], s["z"], math.radians(s["theta_deg"])))

    def progress(r: Runtime) -> None:
        if world is not None:
            p = robot.drive.true_pose
            closest[0] = min(closest[0], world.clearance(p.x, p.z))
        ticks[0] += 1
        if live is not None:
            live.tick(every_s)
            for msg in live.new_events():        # what the re-planner did, as it happens (the loop's thread:
                printer.say(f"goto: {msg}", stream=sys.stdout)   # written by the printer's, never blocking)
        if ticks[0] % round(1.0 / every_s):
            return
        s = controller.status()
        p = estimate(s) if "x" in s else None
        where = (f"at x={p.x:+.2f} z={p.z:+.2f} th={math.degrees(p.theta):+.1f}{frame}  "
                 f"{s['distance_m']:.2f} m to go" if p is not None else "waiting for the first VSLAM pose")
        printer(f"goto: {s.get('state')}  {where}  references {stage.stats['handoffs'] + 1}  "
                f"{'ok' if r.safety.may_move else 'STOP ' + ', '.join(r.safety.reasons())}")

    if live is not None:
        live.start()
    result = None
    try:
        result = rt.run(args.duration, progress, progress_every_s=every_s)
    finally:
        with finishing():           # a second Ctrl-C must not cut the recording short
            try:
                if live is not None:
                    live.stop()
            finally:
                link.close(result)
    printer.done()
    map_refused = None
    if live is not None:
        for msg in live.new_events():
            print(f"goto: {msg}")
        print(live.summary())
        if args.map_out:
            from vbnav.control.line_map_file import MapFileError
            try:
                with finishing("saving the map as grown while driving"):    # nor lose the grown map
                    live.save(args.map_out)
                print(f"map as grown while driving -> {args.map_out}")
            except MapFileError as exc:     # the goto's own summary is still said
                map_refused = exc
                print(f"vbnav goto: --map-out: {exc}; the map as grown while driving was not saved",
                      file=sys.stderr)
    s = controller.status()
    print(f"goto ended: {result.reason} ({result.message})")
    shown_goal = in_goal_frame(goal)
    if "x" in s:
        p = estimate(s)
        print(f"estimated pose: x={p.x:+.3f} m z={p.z:+.3f} m theta={math.degrees(p.theta):+.2f} deg; "
              f"goal x={shown_goal.x:+.3f} z={shown_goal.z:+.3f} theta={math.degrees(shown_goal.theta):+.2f}{frame}")
    true = robot.true_pose()           # the simulator's ground truth, on the simulated robot only
    if true is not None:
        err = math.hypot(true.x - goal.x, true.z - goal.z)
        t = in_goal_frame(true)
        print(f"simulator ground truth: x={t.x:+.3f} z={t.z:+.3f} theta={math.degrees(t.theta):+.2f} deg{frame} "
              f"(position error {err * 100:.1f} cm, heading error "
              f"{math.degrees(abs(math.remainder(true.theta - goal.theta, math.tau))):.2f} deg)")
        if math.isfinite(closest[0]):
            print(f"simulator ground truth: closest approach of the robot centre to a wall or box {closest[0]:.3f} m")
    for e in result.event_report():
        if isinstance(e, str):
            print(f"safety: {e}")
        elif e.kind not in ("hold", "hold_changed") or result.reason != "finished":
            print(f"safety {e.kind}: {e.cause}: {e.message}")
    if result.reason == "signal":
        return 130
    if result.reason in DEVICE_FAULTS:     # a device failed or is not there
        return 3
    # a --record or --map-out not made
    return 0 if result.reason == "finished" and link.recording_error is None and map_refused is None else 1

