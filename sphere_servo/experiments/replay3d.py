"""
``replay3d``: a 3-D replay page of a run, made from its recorded rosbag2.

    python -m sphere_servo.experiments.replay3d BAG [-o OUT.html] [--config NAME]
                                                [--every-image] [--image-topic T]

Writes one self-contained HTML file (default ``replay.html`` beside the bag directory, i.e.
``runs/<ts>/replay.html``) that opens offline in a WebGL browser: the meshcat viewer
(three.js, from the ``meshcat`` package) and every mesh are inlined, nothing is fetched.
It shows the UR5 (its example-robot-data meshes) moving through the run's recorded
``joint_states``, the target and its marks, the camera's frustum and its path so far, and
the desired camera (green frustum). The meshcat panel (top right, open) has play, pause,
reset and the time slider under *Animations*; drag to orbit, scroll to zoom.

The geometry is :class:`sphere_servo.sim.scene.Scene`'s, for the ``arm_sim`` parameters of
the scenario the run used (``--config``, default ``special_sphere``: hand-eye transform,
target pose and target; :func:`sphere_servo.bag.run.run_scene`); the page is refused when
the bag's ground truth ``ground_truth/camera_pose`` and that arm disagree (another scene
recorded it), when its camera is not the bag's ``camera_info`` (size and intrinsics), or
when the bag's measurements see a mark its target does not have (:func:`check_scenario`;
a target of another size or shape is not seen). The desired camera is the taught image's
ground-truth pose, else the scenario's ``desired_cMo``.

The frames are the images' stamps (``--image-topic``, ``sensor_msgs/msg/Image`` or
``CompressedImage``: only their headers are read, so a camera bag recorded compressed is
read as well: ``--image-topic /camera/image_raw/compressed``). Images stamped 0 (unset) are
refused: the frames could not be told apart. A recorded joint
state that no arm can be in (not one finite number per joint, or beyond the URDF's
position limits) is left out like a lost one (no key) and the tool says how many.

What is drawn is the scene's markers (:meth:`Scene.markers`, what RViz or Foxglove will
show of a live run), each at ``/meshcat/<namespace>/<id>``. The page's address may carry
options after ``#``: ``hide=NS,...`` hides those namespaces (``robot``, ``camera``,
``target``, ``camera_path``, ``desired_camera``), ``t=SECONDS`` pauses the animation at
that time (the tests take screenshots with them; e.g. ``replay.html#t=0&hide=robot``).
"""
from __future__ import annotations

import argparse
import base64
import dataclasses
from pathlib import Path
import sys
import time
import warnings

import numpy as np
import pinocchio as pin

from sphere_servo.bag.bagio import BagError
from sphere_servo.bag.offline import IMAGE_TOPIC, load_settings
from sphere_servo.bag.run import (cli_error, load_arm_params, output_path, print_warnings,
                                  read_run, Run, run_scene)
from sphere_servo.core.camera_models import calibrated_camera
from sphere_servo.experiments.video import check_stamps, prepare_output, unrecorded_iterations
from sphere_servo.pipeline.arm_sim import sim_arm
from sphere_servo.sim.scene import (MarkerKind, MarkerSpec, package_dirs, PACKAGE_SCHEME,
                                    resolve_uri, Scene, SceneError)

#: the marker namespaces that move with the run (the others: target, desired_camera)
MOVING = ('robot', 'camera')
#: where the page's viewer camera starts, world frame (m), looking at the world origin
VIEW_FROM = (1.0, 0.8, 0.6)
MAX_PATH_SEGMENTS = 120
#: a joint state further than this (rad) beyond a URDF position limit is not the arm's
LIMIT_TOL = 1e-6


class Recorder:
    """A meshcat "window" that keeps the commands instead of sending them to a server."""

    def __init__(self):
        self.commands: list[bytes] = []

    def send(self, command) -> None:
        import umsgpack
        self.commands.append(umsgpack.packb(command.lower()))


def robot_meshes(scene: Scene) -> dict[Path, object]:
    """
    Load the robot's visual meshes as Pinocchio loads its geometry: resolved file → BVH.

    Pinocchio's own visual geometry model of the URDF (its loader, the scale applied). The
    page gets their triangles, not the files: three.js's Collada loader in meshcat's viewer
    drops parts of the UR5's visual DAE files (Pinocchio's own MeshcatVisualizer shows the
    same).
    """
    pkgs = {m.uri[len(PACKAGE_SCHEME):].partition('/')[0] for m in scene.meshes
            if m.uri.startswith(PACKAGE_SCHEME)}
    dirs = [str(d) for pkg in sorted(pkgs) for d in package_dirs(scene.arm.urdf_path, pkg)]
    try:
        geom = pin.buildGeomFromUrdf(scene.model, str(scene.arm.urdf_path),
                                     pin.GeometryType.VISUAL, package_dirs=dirs)
    except (RuntimeError, ValueError) as exc:
        raise SceneError(f'cannot load the meshes of {scene.arm.urdf_path}: {exc}') from None
    return {Path(g.meshPath).resolve(): g.geometry for g in geom.geometryObjects}


def valid_joints(run: Run, model) -> tuple[Run, int]:
    """
    Return ``run`` without the joint states the arm cannot be in, and how many they were.

    Kept: one finite number per joint of ``model`` (a Pinocchio model), each within its
    position limits (:data:`LIMIT_TOL`). The others are left out as a lost one is.
    """
    lo, hi = model.lowerPositionLimit - LIMIT_TOL, model.upperPositionLimit + LIMIT_TOL
    good = {st: q for st, q in run.joints.items()
            if q.shape == (model.nq,) and np.all(np.isfinite(q)) and np.all(lo <= q)
            and np.all(q <= hi)}
    return dataclasses.replace(run, joints=good), len(run.joints) - len(good)


def check_scenario(run: Run, scene: Scene) -> None:
    """
    Refuse (BagError) a scene whose camera or target is not the one the bag recorded.

    The camera: the bag's first ``camera_info`` (when it reads as a pinhole) against the
    scene's size and intrinsics (not its distortion model). A camera_info with binning or
    an roi (a crop_decimate stream of the simulator's images) matches as its calibrated
    camera, or as the camera of its reduced images; refused, it is named with its binning
    and roi. The target: every mark the recorded measurements name must be one of the
    scene's. Its size is not checked: the
    measured ``r_delta`` depends on the detector's intrinsics, off on purpose in the
    ``calibration_error`` scenario (its own bag measures a 5 cm sphere as 3.8 cm).
    """
    cam, rec = scene.camera, run.camera
    if rec is not None:
        red, full = rec.reduction, calibrated_camera(rec)
        if not any(np.allclose(_intrinsics(cam), _intrinsics(c), rtol=1e-6, atol=1e-6)
                   for c in (rec, full)):
            how = '' if red is None else f': {red}, px={full.px:g} there'
            raise BagError(f"{run.path}: the bag's camera_info ({rec.width}x{rec.height}, "
                           f'px={rec.px:g}{how}) is not the camera of this scenario '
                           f'({cam.width}x{cam.height}, px={cam.px:g}): give --config the '
                           'run was recorded with')
    names = {k[:-2] for m in run.meas.values() for k in m
             if k.endswith('_u') and k != 'ellipse_u'}
    if names - set(scene.target.marks):
        raise BagError(f"{run.path}: the bag's measurements see marks "
                       f'{", ".join(sorted(names - set(scene.target.marks)))} that the target '
                       f'of this scenario has not ({", ".join(scene.target.marks)}): give '
                       '--config the run was recorded with')


def _intrinsics(cam) -> tuple:
    return cam.width, cam.height, cam.px, cam.py, cam.u0, cam.v0


def _mesh(spec: MarkerSpec, meshes: dict):
    """Build the meshcat object of a mesh marker: the triangles of its file (``meshes``)."""
    import meshcat.geometry as mg
    from pinocchio.visualize.meshcat_visualizer import loadMesh
    path = resolve_uri(spec.mesh_uri).resolve()
    if path not in meshes:
        raise SceneError(f"mesh {path} is not one of the robot's visual meshes")
    geom = loadMesh(meshes[path])
    if not isinstance(geom, mg.TriangularMeshGeometry):
        raise SceneError(f'mesh {path} has no triangles')
    return mg.Mesh(geom, mg.MeshPhongMaterial(color=_hex(spec.rgba), shininess=40))


def _hex(rgba) -> int:
    r, g, b = (int(round(float(c) * 255.0)) for c in rgba[:3])
    return (r << 16) + (g << 8) + b


def _object(spec: MarkerSpec, meshes: dict):
    """Build the meshcat object drawing a :class:`MarkerSpec` (in its own frame)."""
    import meshcat.geometry as mg
    if spec.kind == MarkerKind.MESH_RESOURCE:
        return _mesh(spec, meshes)
    if spec.kind == MarkerKind.SPHERE:
        return mg.Mesh(mg.Ellipsoid(np.asarray(spec.scale) / 2),
                       mg.MeshPhongMaterial(color=_hex(spec.rgba)))
    if spec.kind in (MarkerKind.LINE_LIST, MarkerKind.LINE_STRIP):
        geom = mg.PointsGeometry(np.asarray(spec.points, dtype=np.float32).T)
        mat = mg.LineBasicMaterial(color=_hex(spec.rgba), linewidth=2.0)
        return (mg.LineSegments if spec.kind == MarkerKind.LINE_LIST else mg.Line)(geom, mat)
    raise SceneError(f'no drawing for marker kind {spec.kind!r}')


def build_commands(scene: Scene, run: Run, fps: float) -> tuple[list[bytes], float]:
    """
    List the meshcat commands of the replay, in order, and the animation's duration (s).

    What is drawn is the scene's markers (:meth:`Scene.markers`, what a ROS viewer shows),
    each at ``/meshcat/<ns>/<id>``; one animation key per run frame with a recorded joint
    state moves the robot's meshes and the camera (a frame whose joint state the recorder
    lost gets no key: the viewer interpolates between its neighbours), and shows each piece
    of the camera's path from the frame the camera reaches its end on.
    """
    with warnings.catch_warnings():  # meshcat imports its server, on a deprecated pyzmq API
        warnings.simplefilter('ignore', DeprecationWarning)
        import meshcat
    from meshcat.animation import Animation
    rec = Recorder()
    vis = meshcat.Visualizer(window=rec)
    index = {st: k for k, st in enumerate(run.frames)}
    frames = [st for st in run.frames if st in run.joints]
    if not frames:
        raise BagError(f'{run.path}: no joint state for any frame of the run')
    ks = [index[st] for st in frames]  # their frame numbers in the run
    qs = [run.joints[st] for st in frames]
    path = np.array([scene.camera_pose(q).translation for q in qs])
    n = len(frames)
    step = max(1, int(np.ceil((n - 1) / MAX_PATH_SEGMENTS)))
    pieces = [(a, min(a + step, n - 1)) for a in range(0, n - 1, step)]
    meshes = robot_meshes(scene)
    for spec in scene.markers(qs[0], mesh_uris='file'):
        vis[f'{spec.ns}/{spec.id}'].set_object(_object(spec, meshes))
        vis[f'{spec.ns}/{spec.id}'].set_transform(spec.pose.homogeneous)
    for j, (a, b) in enumerate(pieces):  # the camera_path marker, drawn as it grows
        spec = next(m for m in scene.markers(qs[0], path[a:b + 1]) if m.ns == 'camera_path')
        vis[f'{spec.ns}/{j}'].set_object(_object(spec, meshes))
    anim = Animation(default_framerate=fps)
    for k, q in zip(ks, qs):
        with anim.at_frame(vis, k) as fr:
            for spec in scene.markers(q):
                if spec.ns in MOVING:
                    fr[f'{spec.ns}/{spec.id}'].set_transform(spec.pose.homogeneous)
    for j, (a, b) in enumerate(pieces):
        # hidden until the camera gets there; a key at the last frame too, so every clip
        # lasts the whole run
        for k, shown in ((ks[0], b == 0), (ks[b], True), (ks[-1], True)):
            fr = anim.at_frame(vis, k)
            fr[f'camera_path/{j}'].set_property('visible', 'boolean', shown)
    # the viewer camera: meshcat's camera sits in a frame rotated +90° about x (y up)
    x, y, z = VIEW_FROM
    vis['/Cameras/default/rotated/<object>'].set_property('position', [x, z, -y])
    vis.set_animation(anim, play=True, repetitions=1)
    return rec.commands, ks[-1] / fps


PAGE = """<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ margin: 0; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#info {{ position: absolute; left: 8px; top: 8px; font: 13px sans-serif; color: #fff;
         background: rgba(0, 0, 0, 0.45); padding: 6px 9px; border-radius: 4px;
         max-width: calc(100% - 300px); }}
</style></head>
<body>
<div id="meshcat-pane"></div>
<div id="info">{info}</div>
<script>
{viewer_js}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
function bytes(b64) {{
  var s = atob(b64), a = new Uint8Array(s.length);
  for (var i = 0; i < s.length; i++) a[i] = s.charCodeAt(i);
  return a;
}}
var commands = [
{commands}
];
commands.forEach(function (c) {{ viewer.handle_command_bytearray(bytes(c)); }});
commands = null;
var opts = new URLSearchParams(window.location.hash.slice(1));
(opts.get("hide") || "").split(",").filter(Boolean).forEach(function (g) {{
  viewer.handle_command({{type: "set_property", path: "/meshcat/" + g,
                          property: "visible", value: false}});
}});
if (opts.has("t")) {{
  var t = parseFloat(opts.get("t"));
  viewer.animator.pause();
  viewer.animator.seek(t);
  viewer.animator.display_progress(t);
}}
viewer.gui.open();
</script>
</body>
</html>
"""


def viewer_js() -> str:
    """Read the meshcat viewer's bundled JavaScript (three.js and all) from the package."""
    import meshcat
    path = Path(meshcat.__file__).parent / 'viewer' / 'dist' / 'main.min.js'
    if not path.is_file():
        raise OSError(f'meshcat viewer script not found at {path}')
    return path.read_text(encoding='utf-8')


def write_page(commands: list[bytes], out: Path, title: str, info: str) -> Path:
    """Write the self-contained page: the viewer script and the commands, inlined."""
    import html
    js = viewer_js()
    if '</script' in js.lower():
        raise OSError('the meshcat viewer script cannot be inlined (it holds </script>)')
    body = ',\n'.join(f'"{base64.b64encode(c).decode("ascii")}"' for c in commands)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(PAGE.format(title=html.escape(title), info=info, viewer_js=js,
                               commands=body), encoding='utf-8')
    return out


def make_replay(run: Run, scene: Scene, out: Path, invalid: int = 0) -> tuple[Path, dict]:
    """
    Write the replay page of ``run`` in ``scene``; return its path and a few figures.

    Joint states the arm cannot be in are left out (:func:`valid_joints`); figure
    ``invalid``: how many, ``invalid`` (those the caller left out already) included.
    """
    import html
    t0 = time.monotonic()
    run, more = valid_joints(run, scene.model)
    invalid += more
    fps = run.frame_rate()
    commands, duration = build_commands(scene, run, fps)
    d = run.desired
    posed = sum(st in run.joints for st in run.frames)
    lost = '' if posed == len(run.frames) else \
        f' ({len(run.frames) - posed} without a recorded joint state: interpolated)'
    if invalid:
        lost += f' ({invalid} invalid joint states left out)'
    info = (f'<b>{html.escape(run.path.parent.name or str(run.path))}</b>: '
            f'{len(run.frames)} frames{lost}, {duration:.1f} s. Orange: camera and its frustum; '
            f'yellow: its path; green: the desired camera'
            + (f' ({html.escape(d.how)} image)' if d else ' (scenario)') +
            '. Play / pause / time: <i>Animations</i>, top right.')
    path = write_page(commands, out, f'replay: {run.path}', info)
    return path, {'frames': len(run.frames), 'posed': posed, 'invalid': invalid,
                  'duration': duration, 'fps': fps,
                  'seconds': time.monotonic() - t0, 'bytes': path.stat().st_size}


def parse_args(argv):
    ap = argparse.ArgumentParser(prog='replay3d', description=__doc__.strip().splitlines()[0])
    ap.add_argument('bag', help='rosbag2 directory of the run (runs/<timestamp>/bag)')
    ap.add_argument('-o', '--output', help='page (default: replay.html beside the bag)')
    ap.add_argument('--config', default='special_sphere',
                    help='scenario (or params file) the run used: arm, target, feature set')
    ap.add_argument('--every-image', action='store_true',
                    help='every image of the bag, not only the servo iterations')
    ap.add_argument('--image-topic', default=IMAGE_TOPIC,
                    help='sensor_msgs/Image or CompressedImage topic (default: %(default)s)')
    return ap.parse_args(argv)


def main(argv=None) -> int:
    opts = parse_args(list(sys.argv[1:] if argv is None else argv))
    from sphere_servo.pipeline.config import ConfigError
    try:
        run = read_run(opts.bag, load_settings(opts.config), opts.image_topic,
                       every_image=opts.every_image)
        print_warnings('replay3d', run)
        check_stamps(run)
        params = load_arm_params(opts.config)
        arm = sim_arm(params)
        run, invalid = valid_joints(run, arm.model)
        if invalid and not run.joints:
            raise BagError(f'{opts.bag}: none of its {invalid} joint states is one the UR5 '
                           f'can be in ({arm.model.nq} finite positions within its limits, '
                           f'named {", ".join(arm.joint_names)}; the bag names '
                           f'{", ".join(run.joint_names)})')
        scene = run_scene(run, params)
        check_scenario(run, scene)
        out = prepare_output(output_path(opts.bag, opts.output, 'replay.html'))
        path, figs = make_replay(run, scene, out, invalid)
    except (BagError, ConfigError, ValueError, OSError) as err:
        return cli_error('replay3d', err)
    invalid, unrecorded = figs['invalid'], unrecorded_iterations(run)
    missing = figs['frames'] - figs['posed']
    print(f'replay3d: {figs["frames"]} frames ({figs["duration"]:.1f} s at {figs["fps"]:g} '
          f'fps) in {figs["seconds"]:.1f} s'
          + (f'; {missing} frames have no recorded joint state (interpolated)' if missing
             else '')
          + (f'; {invalid} invalid joint states (non-finite, wrong size or beyond the joint '
             'limits) left out' if invalid else '')
          + (f'; the servo counted {unrecorded} more iterations, whose servo/state the bag '
             'does not have (not in the page)' if unrecorded else ''))
    print(f'  {path} ({figs["bytes"] / 1e6:.1f} MB)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
