"""The simulated parallel-jaw gripper, built into an `mujoco.MjSpec` from `sgjax.geometry.gripper.GripperSpec`.

The gripper body's frame IS the sgjax gripper frame (z approach, x closing, origin at the centre of the
closing region's palm-side face), so a Stage-1 grasp (pose[4, 4], width) places it exactly: set the
mocap target to the pose and both finger joints to width / 2.

Structure:
  * `gripper_target`: a mocap body; the trial schedule moves it (pose per step).
  * `gripper`: a free body welded to the target (a soft weld gives finite contact forces when the
    gripper hits something, unlike a kinematic mocap body that would push with infinite mass), holding
    the palm box  |x| <= palm_x/2, |y| <= palm_y/2, -palm_z <= z <= 0.
  * `finger_left` / `finger_right`: children of `gripper` on slide joints along -x / +x. Joint value q
    is the inner face's distance from the centre plane x = 0 (opening width = q_left + q_right), so the
    finger boxes sit exactly where `sgjax.geometry.gripper.gripper_boxes` puts them.
  * Two force-limited position servos, one per finger (ctrl = target q in metres).

All gripper bodies have gravity compensation: the weld then only carries the object, so the gripper
tracks its target to a fraction of a millimetre.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from sgjax.geometry.gripper import GripperSpec

TARGET_BODY = "gripper_target"
GRIPPER_BODY = "gripper"
FINGER_BODIES = ("finger_left", "finger_right")
FINGER_JOINTS = ("finger_left_slide", "finger_right_slide")
FINGER_ACTUATORS = ("finger_left_servo", "finger_right_servo")
PALM_GEOM = "palm"
FINGER_GEOMS = ("finger_left_pad", "finger_right_pad")
GRIPPER_WELD = "gripper_weld"
GRIPPER_GROUP = 2  # geom group of the gripper (the camera's rays skip it)


@dataclasses.dataclass(frozen=True)
class GripperPhysics:
    """Physical values of the simulated gripper (SI units). Defaults and why:

    palm_mass, finger_mass: 0.5 kg and 0.05 kg, the order of a Franka hand (0.73 kg) / Robotiq 2F-85
        fingers; they only matter for the weld and servo dynamics since gravity is compensated.
    grip_force: 25 N per finger, the force limit of each servo. Industrial two-finger grippers give
        20-70 N; 25 N holds the project's objects (< 0.5 kg) with margin at friction 1 but still lets
        off-centre grasps of heavy objects rotate or slip, which the labels must see.
        The gripper's own value is `GripperSpec.closing_force` (default the same 25 N): `add_gripper`
        takes the spec's, unless grip_force was changed from this default (an experiment's override,
        e.g. a weak grip); see `finger_force`.
    servo_kp, servo_kv: 2000 N/m and 20 N s/m, critically damped for a 0.05 kg finger
        (2 sqrt(kp m) = 20); closing commands a target 1 cm beyond closed, so the force saturates at
        grip_force once the finger is more than ~1.3 cm from its goal, i.e. on any object. For a gripper
        whose force is above 25 N both are raised (`servo_gains`) so that this stays true.
    friction: (1.0, 0.005, 0.0001) sliding, torsional (m), rolling (m) of the finger pads, rubber-like.
        The pads' geom priority makes theirs the coefficient of every pad contact, whatever the object's.
        The sliding coefficient comes from `GripperSpec.finger_friction` (default the same 1.0) unless
        friction[0] was changed from this default, as for grip_force; see `pad_friction`.
    condim: 4 (sliding + torsional friction) on the pads: resists an object spinning about the closing
        axis at a single contact point, as a real soft pad does.
    pad_solref, pad_solimp: (0.005, 1.0) and (0.95, 0.99, 0.001): stiffer contacts than MuJoCo's default
        (0.02 s, 0.9-0.95) on the finger pads; the time constant stays >= 2 timesteps for stability. The
        pads' geom priority makes MuJoCo take them as they are for a pad's contacts (without it MuJoCo
        averages a pair's solref and solimp with the object's softer defaults), so a 5 cm box squeezed
        face on sinks ~0.2 mm into each pad at 25 N and ~0.6 mm at 140 N, and a strong grip holds.
    weld_solref: (0.01, 1.0) time constant and damping ratio of the gripper-to-target weld: stiff
        tracking (>= 2 timesteps at 2 ms, as MuJoCo recommends) yet finite forces on impact.
    armature: 0.001 kg on the finger joints, for a well-conditioned servo at a 2 ms step.
    """

    palm_mass: float = 0.5
    finger_mass: float = 0.05
    grip_force: float = 25.0
    servo_kp: float = 2000.0
    servo_kv: float = 20.0
    friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)
    condim: int = 4
    pad_solref: tuple[float, float] = (0.005, 1.0)
    pad_solimp: tuple[float, float, float] = (0.95, 0.99, 0.001)
    weld_solref: tuple[float, float] = (0.01, 1.0)
    armature: float = 0.001

    def __post_init__(self):
        for name in ("friction", "weld_solref", "pad_solref", "pad_solimp"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        for name in ("palm_mass", "finger_mass", "grip_force", "servo_kp", "servo_kv"):
            if not getattr(self, name) > 0:
                raise ValueError(f"GripperPhysics.{name} must be positive, got {getattr(self, name)}")
        if self.condim not in (1, 3, 4, 6):
            raise ValueError(f"GripperPhysics.condim must be 1, 3, 4 or 6, got {self.condim}")


_DEFAULT_PHYSICS = GripperPhysics()


def finger_force(gripper: GripperSpec, physics: GripperPhysics = _DEFAULT_PHYSICS) -> float:
    """The force limit (N) of each finger servo: the spec's closing_force (the single source of the
    gripper's values), or physics.grip_force where that was changed from GripperPhysics's default."""
    if physics.grip_force != _DEFAULT_PHYSICS.grip_force:
        return physics.grip_force
    return gripper.closing_force


def pad_friction(gripper: GripperSpec, physics: GripperPhysics = _DEFAULT_PHYSICS) -> tuple[float, float, float]:
    """(sliding, torsional, rolling) friction of the finger pads: the sliding coefficient is the spec's
    finger_friction, or physics.friction[0] where that was changed from GripperPhysics's default. (The
    palm keeps physics.friction.)"""
    sliding = physics.friction[0] if physics.friction[0] != _DEFAULT_PHYSICS.friction[0] else gripper.finger_friction
    return (sliding, *physics.friction[1:])


def servo_gains(force: float, physics: GripperPhysics = _DEFAULT_PHYSICS) -> tuple[float, float]:
    """(kp, kv) of the finger servos for a force limit `force` (N): physics.servo_kp / servo_kv up to the
    default 25 N; above it kp grows with the force, so that the force still saturates once the finger is
    25 N / servo_kp (1.25 cm) from its goal, and kv with sqrt(kp), so that it stays critically damped."""
    scale = max(1.0, force / _DEFAULT_PHYSICS.grip_force)
    return physics.servo_kp * scale, physics.servo_kv * float(np.sqrt(scale))


def _box_inertia(mass: float, size: np.ndarray) -> np.ndarray:
    """Principal moments of a solid box of full extents size[3]."""
    x, y, z = size
    return mass / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])


def add_gripper(
    spec: mujoco.MjSpec,
    gripper: GripperSpec,
    physics: GripperPhysics = GripperPhysics(),
    home: tuple[float, float, float] = (0.0, 0.0, 2.0),
) -> None:
    """Add the mocap target, the welded gripper, its fingers and servos to `spec` at `home` (z up).

    Sizes, closing force and pad friction come from `gripper` (`finger_force`, `pad_friction`,
    `servo_gains`); the rest of the physics from `physics`."""
    palm = np.asarray(gripper.palm_size)
    finger = np.array([gripper.finger_thickness, gripper.finger_width, gripper.finger_length])
    half_open = 0.5 * gripper.max_opening
    force, pad = finger_force(gripper, physics), pad_friction(gripper, physics)
    kp, kv = servo_gains(force, physics)

    target = spec.worldbody.add_body(name=TARGET_BODY, pos=home, mocap=True)
    del target  # a mocap body needs no geoms; the weld below references it by name

    body = spec.worldbody.add_body(name=GRIPPER_BODY, pos=home, gravcomp=1.0)
    body.add_freejoint(name="gripper_free")
    body.explicitinertial = True
    body.mass = physics.palm_mass
    body.ipos = [0.0, 0.0, -0.5 * palm[2]]
    body.inertia = _box_inertia(physics.palm_mass, palm)
    body.add_geom(
        name=PALM_GEOM,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=0.5 * palm,
        pos=[0.0, 0.0, -0.5 * palm[2]],
        friction=physics.friction,
        condim=physics.condim,
        group=GRIPPER_GROUP,
        rgba=[0.3, 0.3, 0.35, 1.0],
    )

    for side, (name, joint, geom, actuator) in enumerate(
        zip(FINGER_BODIES, FINGER_JOINTS, FINGER_GEOMS, FINGER_ACTUATORS)
    ):
        sign = -1.0 if side == 0 else 1.0  # left finger on -x, right on +x
        # The body origin stays on the centre plane at q = 0; its box lies outside the inner face x = sign*q.
        child = body.add_body(name=name, gravcomp=1.0)
        child.explicitinertial = True
        child.mass = physics.finger_mass
        centre = [sign * 0.5 * finger[0], 0.0, 0.5 * finger[2]]
        child.ipos = centre
        child.inertia = _box_inertia(physics.finger_mass, finger)
        child.add_joint(
            name=joint,
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[sign, 0.0, 0.0],
            range=[0.0, half_open],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=physics.armature,
            solref_limit=[0.004, 1.0],  # stiff stop: closing on nothing, the fingers overlap ~1 mm
        )
        child.add_geom(
            name=geom,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=0.5 * finger,
            pos=centre,
            friction=pad,
            condim=physics.condim,
            solref=physics.pad_solref,
            solimp=[*physics.pad_solimp, 0.5, 2.0],  # (dmin, dmax, width) + MuJoCo's default midpoint, power
            priority=1,  # a pad's contacts take its solref/solimp (and friction, condim), not an average
            group=GRIPPER_GROUP,
            rgba=[0.2, 0.2, 0.25, 1.0],
        )
        servo = spec.add_actuator(name=actuator, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        servo.set_to_position(kp=kp, kv=kv)
        servo.ctrlrange = [-0.01, half_open]
        servo.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        servo.forcerange = [-force, force]
        servo.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    # The fingers meet at q = 0; they never need to collide with each other.
    spec.add_exclude(bodyname1=FINGER_BODIES[0], bodyname2=FINGER_BODIES[1])

    weld = spec.add_equality(
        name=GRIPPER_WELD,
        type=mujoco.mjtEq.mjEQ_WELD,
        objtype=mujoco.mjtObj.mjOBJ_BODY,
        name1=GRIPPER_BODY,
        name2=TARGET_BODY,
    )
    # anchor (3), relative pose (pos 3, quat 4) = identity, torque scale: the frames coincide.
    weld.data = [0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1] + [0.0] * (len(weld.data) - 11)
    weld.solref = physics.weld_solref


def contact_sensor_names(object_names: list[str]) -> list[str]:
    """Sensor order of `add_contact_sensors`: [gripper-table] + per object [gripper, left, right]."""
    names = ["touch_table"]
    for name in object_names:
        names += [f"touch_{name}", f"touch_left_{name}", f"touch_right_{name}"]
    return names


def add_contact_sensors(spec: mujoco.MjSpec, object_names: list[str], table_geom: str) -> None:
    """Contact sensors ("found": number of contacts) of the gripper with the table and every object.

    Order as `contact_sensor_names`. The C engine evaluates them; MJX cannot (body matching is not
    implemented there), so the MJX backend derives the same counts from its contact list.
    """
    names = iter(contact_sensor_names(object_names))

    def add(first: tuple[mujoco.mjtObj, str], second: tuple[mujoco.mjtObj, str]) -> None:
        sensor = spec.add_sensor(name=next(names), type=mujoco.mjtSensor.mjSENS_CONTACT)
        sensor.objtype, sensor.objname = first
        sensor.reftype, sensor.refname = second
        sensor.intprm = [1, 0, 1]  # data = found, no reduction, one slot
        sensor.dim = 1

    subtree = (mujoco.mjtObj.mjOBJ_XBODY, GRIPPER_BODY)
    add(subtree, (mujoco.mjtObj.mjOBJ_GEOM, table_geom))
    for name in object_names:
        target = (mujoco.mjtObj.mjOBJ_BODY, name)
        add(subtree, target)
        add((mujoco.mjtObj.mjOBJ_BODY, FINGER_BODIES[0]), target)
        add((mujoco.mjtObj.mjOBJ_BODY, FINGER_BODIES[1]), target)
