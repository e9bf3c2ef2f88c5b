"""ASF/AMC and BVH readers, the BVH writer and the human body model built from a skeleton.

Forward kinematics is checked against a second implementation written here from the Acclaim spec in
a different form (4x4 local frames chained bone to bone, as the CMU reference player does, with scipy
rotations and its own parsing of the text), not against numbers printed by the code under test.
"""

import textwrap

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtrack.io import (
    PAPER_DOFS,
    Motion,
    human_description,
    human_joint_values,
    joint_positions,
    locked_motion,
    read_amc,
    read_asf,
    read_bvh,
    tapered_capsule,
    write_bvh,
)
from jaxtrack.io._mocap import euler_angles, euler_rotation

CMU_MM_PER_UNIT = 25.4 / 0.45  # data README: 1 unit = 0.05644 m

TINY_ASF = textwrap.dedent(
    """\
    # a three-bone arm with a tilted local frame, units like CMU's
    :version 1.10
    :name TINY
    :units
      mass 1.0
      length 0.45
      angle deg
    :root
       order TX TY TZ RX RY RZ
       axis XYZ
       position 0 0 0
       orientation 0 0 0
    :bonedata
      begin
         id 1
         name upper
         direction 1 0 0
         length 5
         axis 10 -30 40  XYZ
        dof rx ry rz
        limits (-90 90)
               (-45 45)
               (-30 60)
      end
      begin
         id 2
         name lower
         direction 0 -0.6 0.8
         length 4
         axis 0 0 20  XYZ
        dof rx
        limits (0.0 150.0)
      end
      begin
         id 3
         name side
         direction 0 0 1
         length 2
         axis 0 0 0  XYZ
      end
    :hierarchy
      begin
        root upper side
        upper lower
      end
    """
)

TINY_AMC = textwrap.dedent(
    """\
    # two frames
    :FULLY-SPECIFIED
    :DEGREES
    1
    root 1 2 3 10 20 30
    upper 15 -25 35
    lower 60
    2
    root -4 0.5 2 -5 40 -70
    upper -80 10 5
    lower 120
    """
)


# ------------------------------------------------------------------------------ reference FK (test-only)


def _reference_asf(text: str):
    """Bones {name: (direction*length in units, axis degrees, dof list)}, parent map, root order."""
    bones, parent, current = {}, {}, None
    section = None
    for raw in text.splitlines():
        line = raw.split("#")[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            section = line[1:].split()[0]
            continue
        words = line.split()
        if section == "bonedata":
            if words[0] == "begin":
                current = {"dof": []}
            elif words[0] == "end":
                bones[current["name"]] = (
                    np.array(current["direction"], float) * current["length"],
                    np.array(current["axis"], float),
                    current["dof"],
                )
            elif words[0] == "name":
                current["name"] = words[1]
            elif words[0] == "direction":
                current["direction"] = [float(w) for w in words[1:4]]
            elif words[0] == "length":
                current["length"] = float(words[1])
            elif words[0] == "axis":
                assert words[4] == "XYZ"
                current["axis"] = [float(w) for w in words[1:4]]
            elif words[0] == "dof":
                current["dof"] = words[1:]
        elif section == "hierarchy" and words[0] not in ("begin", "end"):
            for child in words[1:]:
                parent[child] = words[0]
    return bones, parent


def _reference_frames(text: str) -> list[dict[str, list[float]]]:
    frames = []
    for raw in text.splitlines():
        line = raw.split("#")[0].strip()
        if not line or line.startswith(":"):
            continue
        words = line.split()
        if len(words) == 1 and words[0].isdigit():
            frames.append({})
        else:
            frames[-1][words[0]] = [float(w) for w in words[1:]]
    return frames


def _rot(axis_deg) -> np.ndarray:
    """Acclaim "XYZ": rotate about x, then y, then z (extrinsic xyz in scipy's naming)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", axis_deg, degrees=True).as_matrix()
    return out


def _reference_positions(asf_text: str, frame: dict[str, list[float]], mm_per_unit: float) -> dict[str, np.ndarray]:
    """Far end of every bone (and the root position), mm: each bone's local frame is reached from its
    parent's local frame by [C_p⁻¹·C_b | C_p⁻¹·(parent segment)] and then turned by its AMC rotation."""
    bones, parent = _reference_asf(asf_text)
    root = frame["root"]
    root_frame = np.eye(4)
    root_frame[:3, 3] = np.array(root[:3]) * mm_per_unit
    root_frame = root_frame @ _rot(root[3:6])
    frames = {"root": (root_frame, np.eye(4), np.zeros(3))}  # world frame of the bone's local axes, C, segment
    out = {"root": root_frame[:3, 3]}

    def visit(name):
        segment, axis, dofs = bones[name]
        c_b = _rot(axis)
        parent_world, c_p, parent_segment = frames[parent[name]]
        step = np.linalg.inv(c_p) @ c_b
        step[:3, 3] = (np.linalg.inv(c_p)[:3, :3] @ parent_segment) * mm_per_unit
        angles = dict(zip(dofs, frame.get(name, [0.0] * len(dofs))))
        motion = _rot([angles.get("rx", 0.0), angles.get("ry", 0.0), angles.get("rz", 0.0)])
        world = parent_world @ step @ motion
        frames[name] = (world, c_b, segment)
        tip_local = np.linalg.inv(c_b)[:3, :3] @ segment * mm_per_unit
        out[name] = world[:3, :3] @ tip_local + world[:3, 3]
        for child in [c for c, p in parent.items() if p == name]:
            visit(child)

    for child in [c for c, p in parent.items() if p == "root"]:
        visit(child)
    return out


# ------------------------------------------------------------------------------ fixtures


@pytest.fixture
def tiny(tmp_path):
    (tmp_path / "tiny.asf").write_text(TINY_ASF)
    (tmp_path / "tiny.amc").write_text(TINY_AMC)
    skeleton = read_asf(tmp_path / "tiny.asf")
    return skeleton, read_amc(tmp_path / "tiny.amc", skeleton)


@pytest.fixture(scope="module")
def walk(shared_data):
    skeleton = read_asf(shared_data / "mocap" / "07-walk.asf")
    return skeleton, read_amc(shared_data / "mocap" / "07_05-walk.amc", skeleton)


# ------------------------------------------------------------------------------ rotations


@pytest.mark.parametrize("order", ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx"])
def test_euler_angles_invert_euler_rotation(order):
    rng = np.random.default_rng(1)
    angles = np.stack([rng.uniform(-3, 3, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(-3, 3, 200)], -1)
    rot = euler_rotation(order, angles)
    np.testing.assert_allclose(euler_angles(order, rot), angles, atol=1e-12)
    # product order: R_a R_b R_c with fixed axes = scipy's intrinsic (upper case) convention
    np.testing.assert_allclose(rot, Rotation.from_euler(order.upper(), angles).as_matrix(), atol=1e-12)
    angles[:, 1] = np.pi / 2  # gimbal lock: the angles are not unique but the rotation is recovered
    locked = euler_rotation(order, angles)
    np.testing.assert_allclose(euler_rotation(order, euler_angles(order, locked)), locked, atol=1e-12)


# ------------------------------------------------------------------------------ ASF / AMC


def test_tiny_asf_fields(tiny):
    skeleton, motion = tiny
    assert skeleton.names == ("root", "upper", "lower", "side")
    assert skeleton.parents.tolist() == [-1, 0, 1, 0]
    assert skeleton.dof_names == (
        "root_tx",
        "root_ty",
        "root_tz",
        "root_rx",
        "root_ry",
        "root_rz",
        "upper_rx",
        "upper_ry",
        "upper_rz",
        "lower_rx",
    )
    assert skeleton.rotation_orders == ("zyx", "zyx", "x", "")
    assert skeleton.length_unit_mm == pytest.approx(CMU_MM_PER_UNIT)
    np.testing.assert_allclose(skeleton.tips[1], [5 * CMU_MM_PER_UNIT, 0, 0])
    np.testing.assert_allclose(skeleton.offsets[2], skeleton.tips[1])  # an ASF bone starts at its parent's end
    np.testing.assert_allclose(np.degrees(skeleton.limits[6:]), [[-90, 90], [-45, 45], [-30, 60], [0, 150]])
    assert np.all(np.isinf(skeleton.limits[:6]))
    assert motion.values.shape == (2, 10) and motion.frame_rate == 120.0
    np.testing.assert_allclose(motion.column("root_tx"), [1 * CMU_MM_PER_UNIT, -4 * CMU_MM_PER_UNIT])
    np.testing.assert_allclose(np.degrees(motion.column("lower_rx")), [60, 120])


def test_tiny_fk_matches_reference(tiny):
    skeleton, motion = tiny
    for f, frame in enumerate(_reference_frames(TINY_AMC)):
        expected = _reference_positions(TINY_ASF, frame, CMU_MM_PER_UNIT)
        ends = joint_positions(skeleton, motion.values[f], ends=True)
        for b, name in enumerate(skeleton.names):
            np.testing.assert_allclose(ends[b], expected[name], atol=1e-9, err_msg=name)
        # each bone's joint is its parent's far end
        starts = joint_positions(skeleton, motion.values[f])
        np.testing.assert_allclose(starts[1:], ends[skeleton.parents[1:]], atol=1e-9)


@pytest.mark.shared
def test_walk_fk_matches_reference(walk, shared_data):
    skeleton, motion = walk
    asf_text = (shared_data / "mocap" / "07-walk.asf").read_text()
    frames = _reference_frames((shared_data / "mocap" / "07_05-walk.amc").read_text())
    assert skeleton.num_bones == 31 and len(skeleton.dof_names) == 62 and motion.num_frames == len(frames) == 517
    # The file's directions are unit to 6 digits (0.34202 -0.939693 0); the reader normalises them, the
    # reference does not: 1e-3 mm covers that over a 2 m chain.
    for f in (0, 150, 516):
        expected = _reference_positions(asf_text, frames[f], CMU_MM_PER_UNIT)
        ends = joint_positions(skeleton, motion.values[f], ends=True)
        for b, name in enumerate(skeleton.names):
            np.testing.assert_allclose(ends[b], expected[name], atol=1e-3, err_msg=f"frame {f} {name}")


@pytest.mark.shared
def test_walk_is_plausible(walk):
    skeleton, motion = walk
    starts = joint_positions(skeleton, motion.values)
    ends = joint_positions(skeleton, motion.values, ends=True)
    # rigid bones: every bone keeps its length in every frame
    np.testing.assert_allclose(
        np.linalg.norm(ends - starts, axis=-1),
        np.broadcast_to(np.linalg.norm(skeleton.tips, axis=-1), starts.shape[:2]),
        atol=1e-9,
    )
    femur = np.linalg.norm(skeleton.tips[skeleton.index("lfemur")])
    assert 300 < femur < 500  # mm: a thigh
    for knee in ("ltibia_rx", "rtibia_rx"):
        angles = np.degrees(motion.column(knee))
        assert -5 < angles.min() and angles.max() < 120 and np.ptp(angles) > 40  # a walking knee flexes
    for elbow in ("lradius_rx", "rradius_rx"):
        angles = np.degrees(motion.column(elbow))
        assert -5 < angles.min() and angles.max() < 150
    # y is up in CMU data: the head stays well above the feet
    head, foot = skeleton.index("head"), skeleton.index("lfoot")
    assert np.all(ends[:, head, 1] - ends[:, foot, 1] > 1200)


@pytest.mark.shared
def test_run_reads(shared_data):
    skeleton = read_asf(shared_data / "mocap" / "09-run.asf")
    motion = read_amc(shared_data / "mocap" / "09_06-run.amc", skeleton)
    assert motion.num_frames == 141
    frame = _reference_frames((shared_data / "mocap" / "09_06-run.amc").read_text())[70]
    expected = _reference_positions((shared_data / "mocap" / "09-run.asf").read_text(), frame, CMU_MM_PER_UNIT)
    ends = joint_positions(skeleton, motion.values[70], ends=True)
    np.testing.assert_allclose(ends[skeleton.index("rtoes")], expected["rtoes"], atol=1e-3)
    assert motion.subsample(5).num_frames == 29 and motion.subsample(5).frame_rate == 24.0


def test_amc_bad_input(tmp_path, tiny):
    skeleton, _ = tiny
    bad = tmp_path / "bad.amc"
    bad.write_text(":DEGREES\n1\nroot 0 0 0 0 0 0\nelbow 3\n")
    with pytest.raises(ValueError, match=r"bad.amc:4: bone 'elbow' is not in the skeleton"):
        read_amc(bad, skeleton)
    bad.write_text(":DEGREES\n1\nroot 0 0 0 0 0 0\nlower 3 4\n")
    with pytest.raises(ValueError, match=r"bad.amc:4: bone 'lower' has 2 values"):
        read_amc(bad, skeleton)
    bad.write_text("# nothing\n")
    with pytest.raises(ValueError, match="no frames"):
        read_amc(bad, skeleton)
    with pytest.raises(ValueError, match="not found"):
        read_amc(tmp_path / "missing.amc", skeleton)


def test_asf_bad_input(tmp_path):
    bad = tmp_path / "bad.asf"
    bad.write_text(TINY_ASF.replace("root upper side", "root upper side ghost"))
    with pytest.raises(ValueError, match="'ghost'"):
        read_asf(bad)
    bad.write_text(TINY_ASF.replace("dof rx\n", "dof rx l\n"))
    with pytest.raises(ValueError, match=r"bone 'lower': DoF 'l' is not supported"):
        read_asf(bad)
    bad.write_text(TINY_ASF.replace("    upper lower\n", ""))
    with pytest.raises(ValueError, match=r"\['lower'\] are not connected"):
        read_asf(bad)
    bad.write_text(":version 1\n")
    with pytest.raises(ValueError, match="not an ASF file"):
        read_asf(bad)


# ------------------------------------------------------------------------------ BVH

HAND_BVH = textwrap.dedent(
    """\
    HIERARCHY
    ROOT Hips
    {
      OFFSET 0 0 0
      CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
      JOINT Arm
      {
        OFFSET 10 0 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        End Site
        {
          OFFSET 0 5 0
        }
      }
      JOINT Leg
      {
        OFFSET 0 -8 0
        CHANNELS 3 Xrotation Yrotation Zrotation
        End Site
        {
          OFFSET 0 -7 0
        }
      }
    }
    MOTION
    Frames: 2
    Frame Time: 0.04
    1 2 3 0 0 0 0 0 0 0 0 0
    0 0 0 90 0 0 0 0 90 30 40 50
    """
)


def test_bvh_hand_computed(tmp_path):
    (tmp_path / "hand.bvh").write_text(HAND_BVH)
    skeleton, motion = read_bvh(tmp_path / "hand.bvh", length_unit_mm=10.0)
    assert skeleton.names == ("Hips", "Arm", "Leg") and skeleton.rotation_orders == ("zxy", "zxy", "xyz")
    assert motion.names[:6] == ("Hips_tx", "Hips_ty", "Hips_tz", "Hips_rz", "Hips_rx", "Hips_ry")
    assert motion.frame_rate == pytest.approx(25.0)
    # frame 0: only the root moves, by (1, 2, 3) cm
    np.testing.assert_allclose(
        joint_positions(skeleton, motion.values[0]), [[10, 20, 30], [110, 20, 30], [10, -60, 30]]
    )
    np.testing.assert_allclose(joint_positions(skeleton, motion.values[0], ends=True)[1], [110, 70, 30])
    # frame 1: hips turned 90° about z: the arm (offset +x) points along +y, its end site (+y) along -x,
    # then the arm's own 90° about y (last in ZXY) swings nothing on the y axis
    pos = joint_positions(skeleton, motion.values[1], ends=True)
    np.testing.assert_allclose(pos[1], [-50, 100, 0], atol=1e-12)
    # the leg's XYZ channels: R = Rz(90) · (Rx(30) Ry(40) Rz(50)) applied to its end site offset
    leg_rot = (
        Rotation.from_euler("z", 90, degrees=True).as_matrix()
        @ Rotation.from_euler("XYZ", [30, 40, 50], degrees=True).as_matrix()
    )
    np.testing.assert_allclose(pos[2], [80, 0, 0] + leg_rot @ [0, -70, 0], atol=1e-12)


def test_asf_to_bvh_round_trip(tmp_path, tiny):
    skeleton, motion = tiny
    path = write_bvh(tmp_path / "tiny.bvh", skeleton, motion, length_unit_mm=10.0)
    skeleton2, motion2 = read_bvh(path, length_unit_mm=10.0)
    assert skeleton2.names == skeleton.names and skeleton2.parents.tolist() == skeleton.parents.tolist()
    assert motion2.frame_rate == pytest.approx(120.0)
    for ends in (False, True):
        np.testing.assert_allclose(
            joint_positions(skeleton2, motion2.values, ends=ends),
            joint_positions(skeleton, motion.values, ends=ends),
            atol=1e-5,
        )


@pytest.mark.shared
def test_walk_to_bvh_round_trip(tmp_path, walk):
    skeleton, motion = walk
    motion = motion.subsample(25)
    skeleton2, motion2 = read_bvh(write_bvh(tmp_path / "walk.bvh", skeleton, motion), length_unit_mm=1.0)
    leaves = [b for b in range(skeleton.num_bones) if not skeleton.children(b)]
    np.testing.assert_allclose(
        joint_positions(skeleton2, motion2.values), joint_positions(skeleton, motion.values), atol=1e-4
    )
    np.testing.assert_allclose(
        joint_positions(skeleton2, motion2.values, ends=True)[:, leaves],
        joint_positions(skeleton, motion.values, ends=True)[:, leaves],
        atol=1e-4,
    )


def test_bvh_bad_input(tmp_path):
    bad = tmp_path / "bad.bvh"
    bad.write_text(
        HAND_BVH.replace("CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Xrotation Wobble")
    )
    with pytest.raises(ValueError, match="'wobble'"):
        read_bvh(bad)
    bad.write_text(HAND_BVH.replace("0 0 0 90 0 0 0 0 90 30 40 50", "0 0 0 90 0 0"))
    with pytest.raises(ValueError, match="frame 1 has 6 values, the hierarchy has 12 channels"):
        read_bvh(bad)
    bad.write_text(HAND_BVH.replace("MOTION", "}\nMOTION"))
    with pytest.raises(ValueError, match="unbalanced"):
        read_bvh(bad)


# ------------------------------------------------------------------------------ human model


def test_tapered_capsule_is_closed_and_outward():
    trimesh = pytest.importorskip("trimesh")
    vertices, faces = tapered_capsule([10.0, 0.0, 0.0], [60.0, 30.0, -20.0], 12.0, 7.0, segments=12)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    length = np.linalg.norm([50.0, 30.0, -20.0])
    # between the volumes of the inscribed cone frustum and the enclosing cylinder with both caps
    frustum = np.pi * length / 3 * (12**2 + 12 * 7 + 7**2)
    assert 0.9 * frustum < mesh.volume < np.pi * 12**2 * (length + 24)


def test_human_model_fk_matches_skeleton(tiny):
    """Every joint of the body model lands where the skeleton's FK puts it, with all DoF and with a subset."""
    from jaxtrack.io import articulated_model

    skeleton, motion = tiny
    for dofs in ("all", {"upper": ("rz", "rx")}):
        body = articulated_model(human_description(skeleton, dofs), dtype=np.float64)
        expected_joints = (
            ("upper_rz", "upper_ry", "upper_rx", "lower_rx") if dofs == "all" else ("upper_rz", "upper_rx")
        )
        assert body.joint_names == expected_joints
        T_world_root, theta = human_joint_values(skeleton, motion, body.joint_names)
        target = joint_positions(skeleton, locked_motion(skeleton, motion, body.joint_names).values)
        for f in range(motion.num_frames):
            poses = body.link_poses(theta[f], T_world_root[f])
            for b, name in enumerate(skeleton.names):
                np.testing.assert_allclose(poses[name][:3, 3], target[f, b], atol=1e-9, err_msg=name)
        if dofs == "all":  # nothing locked: the full motion
            np.testing.assert_allclose(target, joint_positions(skeleton, motion.values))


def test_human_description_bad_input(tiny):
    skeleton, motion = tiny
    with pytest.raises(ValueError, match="bone 'lower' has no rotation DoF 'ry'"):
        human_description(skeleton, {"lower": ("ry",)})
    with pytest.raises(ValueError, match="no bone 'elbow'"):
        human_description(skeleton, {"elbow": ("rx",)})
    with pytest.raises(ValueError, match="'root_tx' is not a rotation DoF"):
        human_joint_values(skeleton, motion, ["root_tx"])
    with pytest.raises(ValueError, match="'upper_tx' is not a rotation DoF"):
        human_joint_values(skeleton, motion, ["upper_tx"])
    with pytest.raises(ValueError, match="motion.names"):
        human_joint_values(skeleton, Motion(("a",), np.zeros((1, 1)), 1.0), [])


@pytest.mark.shared
def test_paper_dofs_on_the_walk(walk):
    from jaxtrack.io import articulated_model

    skeleton, motion = walk
    body = articulated_model(human_description(skeleton, PAPER_DOFS), dtype=np.float64)
    assert body.model.num_dof == 26  # the paper's body model: root 6 + 20 joint angles
    assert {"ltibia_rx", "rtibia_rx", "lradius_rx", "rradius_rx"} <= set(body.joint_names)
    # parts: the root (with pelvis and locked bones merged), one per joint; 21 parts for 20 joints
    assert body.model.num_parts == 21
    parts_with_surface = set(np.unique(np.asarray(body.mesh.vertex_part)).tolist())
    for bone in ("lfemur", "ltibia", "lfoot", "lhumerus", "lradius", "lowerback", "lowerneck"):
        assert body.link_part[bone] in parts_with_surface
    T_world_root, theta = human_joint_values(skeleton, motion, body.joint_names)
    target = joint_positions(skeleton, locked_motion(skeleton, motion, body.joint_names).values)
    for f in (0, 300):
        poses = body.link_poses(theta[f], T_world_root[f])
        for b, name in enumerate(skeleton.names):
            np.testing.assert_allclose(poses[name][:3, 3], target[f, b], atol=1e-6, err_msg=name)
    knee = body.joint_names.index("ltibia_rx")
    np.testing.assert_allclose(theta[:, knee], motion.column("ltibia_rx"))
