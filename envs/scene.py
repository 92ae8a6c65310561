"""Cluttered tabletop scenes: objects dropped onto a table, settled, out-of-workspace objects removed.

A scene is fully determined by (object set, n_objects, seed, SceneConfig). Everything lives in one
compiled `mujoco.MjModel` that also holds the gripper (parked at `home`) and the contact sensors the
grasp trials read, so grasps of a scene roll out from `Scene.state` without recompiling.

Objects are free bodies with one collision geom per convex hull piece (group 3) and a visual mesh
(group 1, no collisions) that the camera's rays hit. Every object body has a weld to the world at its
own parking spot far below the table; the weld is active while the object is parked (before it is
dropped, and after it is removed), so removing an object only edits the state: model shapes stay
fixed, which keeps MJX from recompiling across removals.

World frame: z up, the table top is the plane z = 0, the workspace is |x|, |y| <= workspace_size / 2.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import mujoco
import numpy as np
import trimesh

from envs import gripper_model
from sgjax.geometry.gripper import GripperSpec
from sgjax.stage2.scene_cloud import SceneCloudConfig

TABLE_GEOM = "table"
TABLE_GROUP = 0
VISUAL_GROUP = 1
HULL_GROUP = 3
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
TABLE_PLANE = (0.0, 0.0, 1.0, 0.0)  # the table top z = 0 as (n, d): free space n . x + d > 0
# Geom -> object map values that are not object indices.
TABLE = -1
OTHER = -2


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Scene layout and physics options.

    workspace_size: side of the square workspace on the table (paper: 50 cm).
    table_size: side of the table top; larger than the workspace so that objects rolling just past the
        workspace edge rest on the table (and are removed as out of the workspace) instead of falling.
    drop_radius: drop positions are uniform in |x|, |y| <= drop_radius, for a pile in the workspace.
    drop_clearance: each object is dropped this far above the highest point of the pile so far.
    drop_interval: simulated seconds between two drops (objects fall one at a time, as in VGN piles).
    settle_min_time, settle_max_time: after the last drop, simulate at least / at most this long;
        stop as soon as every object is at rest (speeds below rest_speed, rest_angular_speed).
    object_friction, table_friction: (sliding, torsional, rolling); MuJoCo uses the larger per pair.
    timestep, iterations, ls_iterations, impratio: solver options shared by the scene and the trials
        (Newton, elliptic cones, implicitfast; impratio 10 makes friction nearly hard, so held objects
        do not creep; it needs >= ~20 line-search iterations, with 10 resting objects jitter).
    max_hull_vertices: MuJoCo's maxhullvert for the collision hulls (MJX wants small hulls).
    gripper_home: where the gripper waits while no trial runs; gripper_physics: its physical values.
    surroundings: add what a real camera sees around the table (`add_surroundings`: a floor, a robot
        stand beside the table and a wall behind it) as camera-only geometry: seen by the depth camera
        (labelled OTHER), no collisions, no state, so physics and grasp trials are unchanged. Off by
        default (the table alone, the model as before).
    """

    workspace_size: float = 0.5
    table_size: float = 0.8
    table_thickness: float = 0.05
    drop_radius: float = 0.1
    drop_clearance: float = 0.03
    drop_interval: float = 0.3
    settle_min_time: float = 0.3
    settle_max_time: float = 4.0
    rest_speed: float = 0.005
    rest_angular_speed: float = 0.1
    object_friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)
    table_friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)
    timestep: float = 0.002
    iterations: int = 50
    ls_iterations: int = 30
    impratio: float = 10.0
    max_hull_vertices: int = 64
    gripper_home: tuple[float, float, float] = (0.0, 0.0, 2.0)
    gripper_physics: gripper_model.GripperPhysics = gripper_model.GripperPhysics()
    surroundings: bool = dataclasses.field(default=False, repr=False)  # out of the repr: benchmark resume keys stay

    def __post_init__(self):
        for name in ("object_friction", "table_friction", "gripper_home"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if not 0 < self.workspace_size <= self.table_size:
            raise ValueError(
                f"need 0 < workspace_size <= table_size, got {self.workspace_size}, {self.table_size}"
            )
        if not 0 < self.drop_radius <= 0.5 * self.workspace_size:
            raise ValueError(f"drop_radius must be in (0, workspace_size/2], got {self.drop_radius}")
        if not self.timestep > 0:
            raise ValueError(f"timestep must be positive, got {self.timestep}")


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A settled tabletop scene.

    model: the compiled model (table, objects, gripper, contact sensors).
    state: [nstate] the settled mjSTATE_INTEGRATION state (qpos, qvel, eq_active, mocap, ...).
    assets: [N] the ObjectAsset in each object slot (slots of removed objects included).
    names: [N] body names, "object_<k>".
    body_ids: [N] body ids of the objects.
    present: [N] bool, objects still on the table (False: removed, i.e. parked).
    seed: the seed the scene was made with (-1 for `arrange_scene`); config: its SceneConfig.
    gripper: the GripperSpec the simulated gripper was built from.
    at_rest: whether every present object came to rest within settle_max_time.
    """

    model: mujoco.MjModel
    state: np.ndarray
    assets: tuple
    names: tuple[str, ...]
    body_ids: np.ndarray
    present: np.ndarray
    seed: int
    config: SceneConfig
    gripper: GripperSpec
    at_rest: bool

    @property
    def n_objects(self) -> int:
        return len(self.names)

    def data(self) -> mujoco.MjData:
        """A fresh MjData at the settled state, with mj_forward run (positions, contacts, sensors)."""
        data = mujoco.MjData(self.model)
        mujoco.mj_setState(self.model, data, self.state, STATE_SPEC)
        mujoco.mj_forward(self.model, data)
        return data

    @property
    def qpos(self) -> np.ndarray:
        """[nq] settled joint positions."""
        return self.state[state_slice(self.model, mujoco.mjtState.mjSTATE_QPOS)]

    def object_poses(self) -> np.ndarray:
        """[N, 7] settled object poses (position xyz, quaternion wxyz), parked objects included."""
        qpos = self.qpos
        adr = self.model.jnt_qposadr[self.model.body_jntadr[self.body_ids]]
        return np.stack([qpos[a : a + 7] for a in adr])

    def geom_object(self) -> np.ndarray:
        """[ngeom] object index of each geom; TABLE for the table, OTHER for everything else."""
        return geom_object_map(self.model, self.body_ids)


def workspace_bounds(config: SceneConfig = SceneConfig(), margin: float = 0.05) -> tuple[tuple, tuple]:
    """(lo [3], hi [3]) box of the workspace grown by `margin`, from just below the table top to 1 m
    above: the crop of the Stage-2 scene cloud in labelling and planning alike."""
    half = 0.5 * config.workspace_size + margin
    return (-half, -half, -0.01), (half, half, 1.0)


WORKSPACE_MARGIN = 0.05  # the Stage-2 scene cloud keeps this much around the workspace


def stage2_scene_cloud(
    config: SceneConfig = SceneConfig(), margin: float = WORKSPACE_MARGIN, **settings
) -> SceneCloudConfig:
    """The Stage-2 scene cloud of labelling and the benchmark alike: cropped to the workspace grown by
    `margin`; `settings` (max_points, voxel) override SceneCloudConfig's defaults."""
    return SceneCloudConfig(bounds=workspace_bounds(config, margin), **settings)


def geom_object_map(model: mujoco.MjModel, body_ids: np.ndarray) -> np.ndarray:
    """[ngeom] object index of each geom (hulls and visual mesh), TABLE, or OTHER."""
    body_to_object = np.full(model.nbody, OTHER, np.int32)
    body_to_object[np.asarray(body_ids)] = np.arange(len(body_ids))
    out = body_to_object[model.geom_bodyid]
    out[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, TABLE_GEOM)] = TABLE
    return out


def state_slice(model: mujoco.MjModel, part: mujoco.mjtState) -> slice:
    """Where one component (e.g. mjSTATE_QPOS) lies in a full mjSTATE_INTEGRATION state vector."""
    start = 0
    for bit in range(mujoco.mjtState.mjNSTATE.value):
        component = mujoco.mjtState(1 << bit)
        if not STATE_SPEC & component:
            continue
        size = mujoco.mj_stateSize(model, component)
        if component == part:
            return slice(start, start + size)
        start += size
    raise ValueError(f"{part} is not part of the integration state")


# ---------------------------------------------------------------------------------------------
# Model building.


@functools.lru_cache(maxsize=256)
def _load_mesh(path: str) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # noqa: BLE001 - trimesh raises many types for unreadable files
        raise ValueError(f"cannot read mesh {path!r}: {error}") from None
    if len(mesh.vertices) < 4:
        raise ValueError(f"mesh {path!r} has {len(mesh.vertices)} vertices; need at least 4")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"mesh {path!r} has non-finite vertices")
    return mesh


def _inertia(asset) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass [3] and full inertia [6] (xx, yy, zz, xy, xz, yz) of an asset at its mass.

    From the visual mesh when it is watertight, else from the convex hull of its collision pieces.
    """
    mesh = _load_mesh(asset.visual_path)
    if not mesh.is_volume:
        points = np.concatenate([_load_mesh(p).vertices for p in asset.hull_paths])
        mesh = trimesh.convex.convex_hull(points)
    tensor = mesh.moment_inertia * (asset.mass / mesh.mass)  # about the centre of mass
    full = np.array([tensor[0, 0], tensor[1, 1], tensor[2, 2], tensor[0, 1], tensor[0, 2], tensor[1, 2]])
    return np.asarray(mesh.center_mass), full


def park_position(index: int) -> np.ndarray:
    """Where object `index` waits while parked: far below the table, 1 m from any other."""
    return np.array([10.0 + float(index), 0.0, -10.0])


def object_name(index: int) -> str:
    return f"object_{index}"


def build_spec(assets: Sequence, config: SceneConfig, gripper: GripperSpec) -> mujoco.MjSpec:
    """The scene's MjSpec: table, every object parked, the gripper at home, contact sensors."""
    spec = mujoco.MjSpec()
    spec.modelname = "sgjax_tabletop"
    opt = spec.option
    opt.timestep = config.timestep
    opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    opt.impratio = config.impratio
    opt.iterations = config.iterations
    opt.ls_iterations = config.ls_iterations

    half_table = 0.5 * config.table_size
    spec.worldbody.add_geom(
        name=TABLE_GEOM,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_table, half_table, 0.5 * config.table_thickness],
        pos=[0.0, 0.0, -0.5 * config.table_thickness],
        friction=config.table_friction,
        group=TABLE_GROUP,
        rgba=[0.6, 0.5, 0.4, 1.0],
    )
    if config.surroundings:
        add_surroundings(spec, config)

    meshes: dict[tuple[str, int], str] = {}  # (path, maxhullvert or -1 for visual) -> mesh name

    def mesh_name(path: str, visual: bool) -> str:
        key = (path, -1 if visual else config.max_hull_vertices)
        if key not in meshes:
            mesh = _load_mesh(path)
            name = f"mesh_{len(meshes)}"
            if visual:
                spec.add_mesh(
                    name=name,
                    uservert=np.asarray(mesh.vertices, np.float32).ravel(),
                    userface=np.asarray(mesh.faces, np.int32).ravel(),
                    inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL,  # never used; tolerant of holes
                )
            else:
                spec.add_mesh(
                    name=name,
                    uservert=np.asarray(mesh.vertices, np.float32).ravel(),
                    maxhullvert=config.max_hull_vertices,
                )
            meshes[key] = name
        return meshes[key]

    for index, asset in enumerate(assets):
        name = object_name(index)
        body = spec.worldbody.add_body(name=name, pos=park_position(index))
        body.add_freejoint(name=f"{name}_free")
        com, inertia = _inertia(asset)
        body.explicitinertial = True
        body.mass = float(asset.mass)
        body.ipos = com
        body.fullinertia = inertia
        for piece, path in enumerate(asset.hull_paths):
            body.add_geom(
                name=f"{name}_hull_{piece}",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=mesh_name(path, visual=False),
                friction=config.object_friction,
                group=HULL_GROUP,
                rgba=[0.5, 0.7, 0.9, 0.3],
            )
        body.add_geom(
            name=f"{name}_visual",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=mesh_name(asset.visual_path, visual=True),
            contype=0,
            conaffinity=0,
            group=VISUAL_GROUP,
            rgba=[0.8, 0.3, 0.2, 1.0],
        )
        # relpose quaternion 0 -> MuJoCo takes the relative pose at qpos0, i.e. the parking spot.
        park = spec.add_equality(
            name=f"{name}_park",
            type=mujoco.mjtEq.mjEQ_WELD,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1=name,
            name2="world",
        )
        park.data = [0.0] * len(park.data)
        park.data[10] = 1.0  # torque scale
        park.active = True

    gripper_model.add_gripper(spec, gripper, config.gripper_physics, home=config.gripper_home)
    gripper_model.add_contact_sensors(spec, [object_name(i) for i in range(len(assets))], TABLE_GEOM)
    return spec


FLOOR_HEIGHT = -0.75  # the floor under the table (a 0.75 m table), z of its plane
STAND_SIZE = (0.2, 0.2)  # the robot stand's footprint (x, y)
STAND_ABOVE_TABLE = 0.25  # its top above the table top
STAND_GAP = 0.02  # between the table's +x edge and the stand
STAND_Y = 0.25  # its centre's y: beside the back half of the table, where the default camera sees it
WALL_GAP = 0.1  # between the table's +y edge and the wall
WALL_ABOVE_TABLE = 1.0  # the wall reaches from the floor to this far above the table top
SURROUNDINGS_GEOMS = ("floor", "robot_stand", "wall")


def add_surroundings(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """Camera-only static geometry around the table (`SceneConfig.surroundings`), named
    SURROUNDINGS_GEOMS: a floor plane FLOOR_HEIGHT below the table top; a robot stand (a box of
    STAND_SIZE footprint from the floor to STAND_ABOVE_TABLE above the table top) STAND_GAP off the
    table's +x edge; a wall WALL_GAP behind the table's +y edge, from the floor to WALL_ABOVE_TABLE.
    All in VISUAL_GROUP (the camera's rays hit them; `geom_object` maps them to OTHER) with contype =
    conaffinity = 0 (no contacts) on the world body (no state)."""
    half_table = 0.5 * config.table_size
    sx, sy = 0.5 * STAND_SIZE[0], 0.5 * STAND_SIZE[1]
    stand_half_height = 0.5 * (STAND_ABOVE_TABLE - FLOOR_HEIGHT)
    wall_half_height = 0.5 * (WALL_ABOVE_TABLE - FLOOR_HEIGHT)
    wall_half_width = half_table + 1.0
    wall_half_thickness = 0.01
    common = {"contype": 0, "conaffinity": 0, "group": VISUAL_GROUP}
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.1],
                            pos=[0.0, 0.0, FLOOR_HEIGHT], rgba=[0.5, 0.5, 0.5, 1.0], **common)
    spec.worldbody.add_geom(name="robot_stand", type=mujoco.mjtGeom.mjGEOM_BOX, size=[sx, sy, stand_half_height],
                            pos=[half_table + STAND_GAP + sx, STAND_Y, FLOOR_HEIGHT + stand_half_height],
                            rgba=[0.3, 0.3, 0.3, 1.0], **common)
    spec.worldbody.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX,
                            size=[wall_half_width, wall_half_thickness, wall_half_height],
                            pos=[0.0, half_table + WALL_GAP + wall_half_thickness, FLOOR_HEIGHT + wall_half_height],
                            rgba=[0.9, 0.9, 0.85, 1.0], **common)


def build_sensorless_spec(assets: Sequence, config: SceneConfig, gripper: GripperSpec) -> mujoco.MjSpec:
    """`build_spec` without the contact sensors: MJX cannot evaluate contact sensors with body matching
    (its trials count contacts from the contact list instead, and its ray casts need no sensors)."""
    spec = build_spec(assets, config, gripper)
    for sensor in list(spec.sensors):
        spec.delete(sensor)
    return spec


# ---------------------------------------------------------------------------------------------
# Dropping, settling, removing.


def _free_adr(model: mujoco.MjModel, body_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    joints = model.body_jntadr[body_ids]
    return model.jnt_qposadr[joints], model.jnt_dofadr[joints]


def _park(model, data, index: int, body_id: int) -> None:
    qadr, vadr = _free_adr(model, np.array([body_id]))
    data.qpos[qadr[0] : qadr[0] + 7] = np.concatenate([park_position(index), [1.0, 0.0, 0.0, 0.0]])
    data.qvel[vadr[0] : vadr[0] + 6] = 0.0
    data.eq_active[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, f"{object_name(index)}_park")] = 1


def _speeds(model, data, body_ids: np.ndarray, present: np.ndarray) -> tuple[float, float]:
    _, vadr = _free_adr(model, body_ids[present])
    if len(vadr) == 0:
        return 0.0, 0.0
    v = np.stack([data.qvel[a : a + 6] for a in vadr])
    return float(np.linalg.norm(v[:, :3], axis=1).max()), float(np.linalg.norm(v[:, 3:], axis=1).max())


def _settle(model, data, scene_body_ids, present, config: SceneConfig) -> bool:
    """Step until every present object rests (checked every 50 ms) or settle_max_time; -> at rest."""
    check = max(1, round(0.05 / config.timestep))
    steps_min = round(config.settle_min_time / config.timestep)
    steps_max = round(config.settle_max_time / config.timestep)
    for step in range(0, steps_max, check):
        mujoco.mj_step(model, data, nstep=check)
        if step + check >= steps_min:
            lin, ang = _speeds(model, data, scene_body_ids, present)
            if lin < config.rest_speed and ang < config.rest_angular_speed:
                return True
    return False


def _remove_outside(model, data, body_ids, present, config: SceneConfig) -> None:
    """Park every present object whose centre of mass left the workspace or fell below the table top."""
    half = 0.5 * config.workspace_size
    for index in np.flatnonzero(present):
        x, y, z = data.xipos[body_ids[index]]
        if abs(x) > half or abs(y) > half or z < 0.0:
            _park(model, data, int(index), int(body_ids[index]))
            present[index] = False
    mujoco.mj_forward(model, data)


def _random_quaternion(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _new_scene(assets: Sequence, config: SceneConfig, gripper: GripperSpec):
    """Compile the scene with every object parked: (model, data, body_ids)."""
    model = build_spec(assets, config, gripper).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    body_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, object_name(i)) for i in range(len(assets))])
    return model, data, body_ids


def _release(model, data, index: int, body_id: int, pose: np.ndarray) -> None:
    """Unpark object `index` at pose[7] (position, quaternion wxyz), at rest."""
    qadr, vadr = _free_adr(model, np.array([body_id]))
    data.qpos[qadr[0] : qadr[0] + 7] = pose
    data.qvel[vadr[0] : vadr[0] + 6] = 0.0
    data.eq_active[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, f"{object_name(index)}_park")] = 0


def make_scene(
    objects: Sequence,
    n_objects: int,
    seed: int,
    config: SceneConfig = SceneConfig(),
    gripper: GripperSpec = GripperSpec(),
) -> Scene:
    """Drop n_objects objects drawn from `objects` onto the table, one at a time, and settle them.

    Objects are drawn without replacement while n_objects <= len(objects), else with replacement.
    Each is dropped at a uniform position |x|, |y| <= drop_radius, a uniformly random orientation and
    drop_clearance above the pile so far; then the scene is simulated until at rest and objects outside
    the workspace are removed. Same (objects, n_objects, seed, config, gripper) -> identical state.
    """
    if not objects:
        raise ValueError("objects must not be empty")
    if n_objects < 1:
        raise ValueError(f"n_objects must be >= 1, got {n_objects}")
    rng = np.random.default_rng(seed)
    choice = rng.choice(len(objects), size=n_objects, replace=n_objects > len(objects))
    assets = tuple(objects[i] for i in choice)
    model, data, body_ids = _new_scene(assets, config, gripper)
    present = np.zeros(n_objects, bool)
    radius = np.array([0.5 * float(np.linalg.norm(a.extents)) for a in assets])
    drop_steps = round(config.drop_interval / config.timestep)
    for index in range(n_objects):
        # Highest point of the pile so far, bounded by the objects' spheres.
        top = max([0.0] + [data.xipos[body_ids[j]][2] + radius[j] for j in np.flatnonzero(present)])
        xy = rng.uniform(-config.drop_radius, config.drop_radius, size=2)
        position = [xy[0], xy[1], top + radius[index] + config.drop_clearance]
        _release(model, data, index, body_ids[index], np.concatenate([position, _random_quaternion(rng)]))
        present[index] = True
        mujoco.mj_step(model, data, nstep=drop_steps)
    at_rest = _settle(model, data, body_ids, present, config)
    _remove_outside(model, data, body_ids, present, config)
    return _finish(model, data, assets, body_ids, present, seed, config, gripper, at_rest)


def arrange_scene(
    objects: Sequence,
    poses,
    config: SceneConfig = SceneConfig(),
    gripper: GripperSpec = GripperSpec(),
) -> Scene:
    """A scene with objects[i] placed at poses[i] ([N, 7]: position, quaternion wxyz), then settled.

    For hand-made layouts (tests, reproducing a setup). Poses must not interpenetrate; objects outside
    the workspace after settling are removed. The scene's seed is -1.
    """
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape != (len(objects), 7) or len(objects) == 0:
        raise ValueError(f"poses must have shape [N, 7] with N = len(objects) = {len(objects)}, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("poses must be finite")
    norms = np.linalg.norm(poses[:, 3:], axis=1)
    if (np.abs(norms - 1.0) > 1e-6).any():
        raise ValueError(f"pose quaternions must be unit length, got norms {norms.tolist()}")
    assets = tuple(objects)
    model, data, body_ids = _new_scene(assets, config, gripper)
    for index, pose in enumerate(poses):
        _release(model, data, index, body_ids[index], pose)
    present = np.ones(len(assets), bool)
    at_rest = _settle(model, data, body_ids, present, config)
    _remove_outside(model, data, body_ids, present, config)
    return _finish(model, data, assets, body_ids, present, -1, config, gripper, at_rest)


def _finish(model, data, assets, body_ids, present, seed, config, gripper, at_rest) -> Scene:
    data.time = 0.0
    state = np.empty(mujoco.mj_stateSize(model, STATE_SPEC))
    mujoco.mj_getState(model, data, state, STATE_SPEC)
    return Scene(
        model=model,
        state=state,
        assets=tuple(assets),
        names=tuple(object_name(i) for i in range(len(assets))),
        body_ids=np.asarray(body_ids),
        present=np.asarray(present, bool).copy(),
        seed=seed,
        config=config,
        gripper=gripper,
        at_rest=at_rest,
    )


def after_trial(scene: Scene, qpos: np.ndarray) -> Scene:
    """The scene as a grasp trial left it: objects at their poses in qpos [nq] (a trial's final_qpos),
    the gripper gone (back home), everything released at rest and re-settled; objects that left the
    workspace are removed. A failed grasp that knocked or dropped objects changes the scene for the next
    attempt, as on a real table. Non-finite qpos (an invalid trial) leaves the scene unchanged.
    """
    qpos = np.asarray(qpos, np.float64)
    if qpos.shape != (scene.model.nq,):
        raise ValueError(f"qpos must have shape [{scene.model.nq}], got {qpos.shape}")
    if not np.isfinite(qpos).all():
        return scene
    model = scene.model
    data = scene.data()
    present = scene.present.copy()
    qadr, vadr = _free_adr(model, scene.body_ids)
    for index in np.flatnonzero(present):
        pose = qpos[qadr[index] : qadr[index] + 7].copy()
        pose[3:] /= np.linalg.norm(pose[3:])
        data.qpos[qadr[index] : qadr[index] + 7] = pose
        data.qvel[vadr[index] : vadr[index] + 6] = 0.0
    mujoco.mj_forward(model, data)
    at_rest = _settle(model, data, scene.body_ids, present, scene.config)
    _remove_outside(model, data, scene.body_ids, present, scene.config)
    return _finish(model, data, scene.assets, scene.body_ids, present, scene.seed, scene.config, scene.gripper, at_rest)


def with_gripper(scene: Scene, gripper: GripperSpec, like: Scene | None = None) -> Scene:
    """The same scene state with a simulated gripper built from another GripperSpec (e.g. to replay a
    grasp with another hand from the same objects' poses). The gripper waits at its home, away from the
    table, so no object feels the change; the state is reused as it is. like: an earlier result of this
    function for the same objects, whose compiled model is reused (compiling costs ~0.1 s per object)."""
    if gripper == scene.gripper:
        return scene
    if like is not None and like.gripper == gripper and like.assets == scene.assets and like.config == scene.config:
        return dataclasses.replace(scene, model=like.model, gripper=gripper)
    model = build_spec(scene.assets, scene.config, gripper).compile()
    if mujoco.mj_stateSize(model, STATE_SPEC) != len(scene.state):
        raise ValueError("the gripper changes the scene's state layout; a GripperSpec only changes sizes")
    return dataclasses.replace(scene, model=model, gripper=gripper)


def remove_object(scene: Scene, index: int, settle: bool = True) -> Scene:
    """The scene with object `index` removed (parked), the rest re-settled when `settle` (default).

    Deterministic; the model is shared, only the state changes. Re-settling lets objects that leaned on
    the removed one come to rest, and removes any that then leave the workspace.
    """
    if not 0 <= index < scene.n_objects:
        raise ValueError(f"object index {index} out of range [0, {scene.n_objects})")
    if not scene.present[index]:
        raise ValueError(f"object {index} ({scene.names[index]}) is already removed")
    model = scene.model
    data = scene.data()
    present = scene.present.copy()
    _park(model, data, index, int(scene.body_ids[index]))
    present[index] = False
    at_rest = scene.at_rest
    if settle and present.any():
        at_rest = _settle(model, data, scene.body_ids, present, scene.config)
        _remove_outside(model, data, scene.body_ids, present, scene.config)
    return _finish(model, data, scene.assets, scene.body_ids, present, scene.seed, scene.config, scene.gripper, at_rest)
