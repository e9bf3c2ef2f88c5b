"""URDF models: prismatic joints in chain_model, read_urdf against yourdfpy's own forward kinematics,
read -> write -> read round trips (Panda, the ISB human, the body model built from mocap), mesh
scale/origin/package:// handling, and errors that name the file and element."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
import yourdfpy
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from jaxtrack.geometry import chain_model, part_transforms
from jaxtrack.io import PAPER_DOFS, articulated_model, human_description, read_asf, read_urdf, write_urdf
from jaxtrack.io._urdf import rpy_from_rotation

# yourdfpy's scene building calls a trimesh function that trimesh deprecates
pytestmark = pytest.mark.filterwarnings("ignore:.*Scene.dump.*:DeprecationWarning")
_part_transforms = jax.jit(part_transforms)  # compiled once per model shape (op by op is slower here)

ROBOTS = "articulated/example-robot-data/robots"
PANDA = f"{ROBOTS}/panda_description/urdf/panda.urdf"
ISB_HUMAN = f"{ROBOTS}/human_description/robots/human.urdf"


# ------------------------------------------------------------------------------ chain_model


def test_chain_model_prismatic_joint():
    """A slider on a hinge: the prismatic joint moves its part θ mm along its (rotated) axis."""
    model = chain_model(
        [-1, 0, 1],
        [(0.0, 0.0, 2.0), (3.0, 0.0, 0.0)],
        [(10.0, 0.0, 0.0), (0.0, 0.0, 0.0)],
        dtype=jnp.float64,
        joint_types=["revolute", "prismatic"],
    )
    np.testing.assert_allclose(model.joint_twists[1], [1, 0, 0, 0, 0, 0])
    theta = jnp.array([np.pi / 2, 7.0])
    T = _part_transforms(model, jnp.eye(4, dtype=jnp.float64), theta)
    point = np.array([20.0, 0.0, 0.0, 1.0])
    # the hinge turns about z through (10, 0, 0): the slid point (27, 0, 0) goes to (10, 17, 0)
    np.testing.assert_allclose(T[2] @ point, [10.0, 17.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(T[1] @ point, [10.0, 10.0, 0.0, 1.0], atol=1e-12)
    # revolute stays the default
    default = chain_model([-1, 0], [(0.0, 1.0, 0.0)], [(1.0, 2.0, 3.0)])
    explicit = chain_model([-1, 0], [(0.0, 1.0, 0.0)], [(1.0, 2.0, 3.0)], joint_types=["revolute"])
    np.testing.assert_array_equal(default.joint_twists, explicit.joint_twists)
    with pytest.raises(ValueError, match=r"joint_types\[0\] = 'ball'"):
        chain_model([-1, 0], [(0.0, 1.0, 0.0)], [(0.0, 0.0, 0.0)], joint_types=["ball"])
    with pytest.raises(ValueError, match="prismatic joint axis"):
        chain_model([-1, 0], [(0.0, 0.0, 0.0)], [(0.0, 0.0, 0.0)], joint_types=["prismatic"])


def test_rpy_from_rotation_inverts_urdf_rpy():
    rng = np.random.default_rng(3)
    rotations = Rotation.random(50, random_state=4).as_matrix()
    locked = [Rotation.from_euler("ZYX", [y, s * np.pi / 2, r]).as_matrix() for y, r, s in rng.uniform(-3, 3, (10, 3))]
    for rot in [*rotations, *locked]:
        roll, pitch, yaw = rpy_from_rotation(rot)
        # URDF: R = Rz(yaw) · Ry(pitch) · Rx(roll)
        np.testing.assert_allclose(Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix(), rot, atol=1e-12)


# ------------------------------------------------------------------------------ helpers


def _random_configuration(model, rng):
    """{actuated joint: value} in URDF units within the limits (±π where there are none)."""
    lower = np.where(np.isfinite(model.lower), model.lower, -np.pi) / model.joint_scale
    upper = np.where(np.isfinite(model.upper), model.upper, np.pi) / model.joint_scale
    q = rng.uniform(lower, upper)
    return {name: float(q[j]) for j, name in enumerate(model.joint_names) if model.mimic[j] is None}


def _assert_fk_matches_yourdfpy(path, model, configurations):
    reference = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert set(reference.actuated_joint_names) == {n for j, n in enumerate(model.joint_names) if model.mimic[j] is None}
    for values in configurations:
        reference.update_cfg({name: values[name] for name in reference.actuated_joint_names})
        poses = model.link_poses(model.joint_vector(values))
        assert set(poses) == set(reference.link_map)
        for link, T in poses.items():
            expected = np.array(reference.get_transform(link, reference.base_link))
            expected[:3, 3] *= 1000.0  # m -> mm
            np.testing.assert_allclose(T, expected, atol=1e-9, err_msg=link)


def _face_corners(model) -> np.ndarray:
    """(F, 3, 3) the corners of every face (independent of how vertices were merged or ordered)."""
    return np.asarray(model.mesh.vertices)[np.asarray(model.mesh.faces)]


def _assert_same_model(a, b, mesh_atol):
    assert a.name == b.name
    assert a.joint_names == b.joint_names and a.joint_types == b.joint_types and a.part_names == b.part_names
    assert dict(a.link_part) == dict(b.link_part) and a.mimic == b.mimic
    np.testing.assert_allclose(a.lower, b.lower, rtol=1e-15)
    np.testing.assert_allclose(a.upper, b.upper, rtol=1e-15)
    np.testing.assert_allclose(a.model.joint_twists, b.model.joint_twists, atol=1e-9)
    np.testing.assert_array_equal(a.model.part_joints, b.model.part_joints)
    for link in a.T_root_link0:
        np.testing.assert_allclose(a.T_root_link0[link], b.T_root_link0[link], atol=1e-9, err_msg=link)
    np.testing.assert_array_equal(a.mesh.face_part, b.mesh.face_part)
    np.testing.assert_allclose(_face_corners(a), _face_corners(b), atol=mesh_atol)


# ------------------------------------------------------------------------------ Panda


@pytest.fixture(scope="module")
def panda(shared_data):
    return read_urdf(shared_data / PANDA, geometry="collision", dtype=np.float64)


@pytest.mark.shared
def test_panda_structure(panda):
    assert panda.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8)) + (
        "panda_finger_joint1",
        "panda_finger_joint2",
    )
    assert panda.joint_types == ("revolute",) * 7 + ("prismatic",) * 2
    assert panda.model.num_parts == 10 and panda.mesh.num_faces == 2396  # 10 STL meshes, hand and tcp merged
    # fixed links merge into their parent part
    assert panda.link_part["panda_hand"] == panda.link_part["panda_link8"] == panda.link_part["panda_link7"]
    # limits as data, prismatic in mm; the second finger mimics the first
    np.testing.assert_allclose(panda.lower[3], -3.0718) and np.testing.assert_allclose(panda.upper[3], -0.0698)
    np.testing.assert_allclose(panda.upper[7:], [40.0, 40.0])
    assert panda.mimic[8] == (7, 1.0, 0.0) and panda.mimic[7] is None
    theta = panda.joint_vector({"panda_finger_joint1": 0.03})
    np.testing.assert_allclose(theta[7:], [30.0, 30.0])
    assert panda.joint_values(theta)["panda_finger_joint2"] == pytest.approx(0.03)
    with pytest.raises(ValueError, match=r"\['panda_joint9'\] not in model 'panda'"):
        panda.joint_vector({"panda_joint9": 0.1})


@pytest.mark.shared
def test_panda_fk_matches_yourdfpy(panda, shared_data):
    rng = np.random.default_rng(0)
    _assert_fk_matches_yourdfpy(shared_data / PANDA, panda, [_random_configuration(panda, rng) for _ in range(5)])


@pytest.mark.shared
def test_panda_posed_surface_matches_yourdfpy(panda, shared_data):
    """Our vertices moved by part_transforms (eq. 2) against yourdfpy's collision scene at the same pose."""
    reference = yourdfpy.URDF.load(
        str(shared_data / PANDA), build_scene_graph=False, build_collision_scene_graph=True, load_collision_meshes=True
    )
    values = _random_configuration(panda, np.random.default_rng(1))
    reference.update_cfg({name: values[name] for name in reference.actuated_joint_names})
    expected = np.asarray(reference.collision_scene.to_geometry().vertices) * 1000.0
    T = np.asarray(
        _part_transforms(panda.model, jnp.eye(4, dtype=jnp.float64), jnp.asarray(panda.joint_vector(values)))
    )
    T_vertex = T[np.asarray(panda.mesh.vertex_part)]
    posed = np.einsum("nij,nj->ni", T_vertex[:, :3, :3], np.asarray(panda.mesh.vertices)) + T_vertex[:, :3, 3]
    assert cKDTree(posed).query(expected)[0].max() < 1e-6
    assert cKDTree(expected).query(posed)[0].max() < 1e-6


@pytest.mark.shared
def test_panda_round_trip(panda, tmp_path):
    path = write_urdf(panda, tmp_path / "panda.urdf")
    again = read_urdf(path, dtype=np.float64)
    _assert_same_model(panda, again, mesh_atol=1e-3)  # STL stores float32 mm
    _assert_fk_matches_yourdfpy(path, again, [_random_configuration(again, np.random.default_rng(2))])


@pytest.mark.shared
def test_panda_visual_meshes(shared_data):
    """The COLLADA visual meshes (pycollada through trimesh) give the same kinematics, finer surfaces
    inside the collision hulls' bounds."""
    visual = read_urdf(shared_data / PANDA, geometry="visual")
    collision = read_urdf(shared_data / PANDA, geometry="collision")
    assert visual.joint_names == collision.joint_names and visual.mesh.num_faces > 50 * collision.mesh.num_faces
    np.testing.assert_allclose(visual.model.joint_twists, collision.model.joint_twists, atol=1e-4)
    for part in range(visual.model.num_parts):
        v = np.asarray(visual.mesh.vertices)[np.asarray(visual.mesh.vertex_part) == part]
        c = np.asarray(collision.mesh.vertices)[np.asarray(collision.mesh.vertex_part) == part]
        assert np.all(v.min(0) > c.min(0) - 8.0) and np.all(v.max(0) < c.max(0) + 8.0)  # mm


# ------------------------------------------------------------------------------ human models


@pytest.mark.shared
def test_isb_human_fk_and_round_trip(shared_data, tmp_path):
    """The 36-DoF human of example-robot-data: STL meshes with anisotropic `scale`, 36 revolute joints."""
    human = read_urdf(shared_data / ISB_HUMAN, dtype=np.float64)
    assert human.num_joints == 36 and all(t == "revolute" for t in human.joint_types)
    rng = np.random.default_rng(5)
    _assert_fk_matches_yourdfpy(shared_data / ISB_HUMAN, human, [_random_configuration(human, rng) for _ in range(3)])
    again = read_urdf(write_urdf(human, tmp_path / "human.urdf"), dtype=np.float64)
    _assert_same_model(human, again, mesh_atol=1e-3)


@pytest.fixture(scope="module")
def mocap_body(shared_data, tmp_path_factory):
    """The paper's 26-DoF body model of CMU subject 07, written as URDF and read back."""
    skeleton = read_asf(shared_data / "mocap" / "07-walk.asf")
    path = write_urdf(human_description(skeleton, PAPER_DOFS), tmp_path_factory.mktemp("body") / "body.urdf")
    return path, read_urdf(path, dtype=np.float64)


@pytest.mark.shared
def test_mocap_body_fk_matches_yourdfpy(mocap_body):
    path, body = mocap_body
    assert body.model.num_dof == 26 and "ltibia_rx" in body.joint_names and "lradius_rx" in body.joint_names
    rng = np.random.default_rng(6)
    _assert_fk_matches_yourdfpy(path, body, [_random_configuration(body, rng) for _ in range(3)])


@pytest.mark.shared
def test_mocap_body_round_trip(mocap_body, tmp_path):
    _, body = mocap_body
    again = read_urdf(write_urdf(body, tmp_path / "again.urdf"), dtype=np.float64)
    _assert_same_model(body, again, mesh_atol=1e-3)
    # the in-memory description gives the same model as the file
    direct = articulated_model(body.description, dtype=np.float64)
    _assert_same_model(body, direct, mesh_atol=0.0)


# ------------------------------------------------------------------------------ files made here


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def _box_stl(path, extents=(0.02, 0.04, 0.06)):
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=extents).export(path)
    return path


ARM = """\
    <robot name="arm">
      <link name="base">
        <visual>
          <origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/>
          <geometry><mesh filename="{mesh}" scale="2 1 1"/></geometry>
        </visual>
      </link>
      <link name="upper">
        <visual><geometry><box size="0.1 0.2 0.3"/></geometry></visual>
        <collision><geometry><cylinder radius="0.05" length="0.2"/></geometry></collision>
      </link>
      <link name="tool"><visual><geometry><sphere radius="0.01"/></geometry></visual></link>
      <joint name="shoulder" type="{kind}">
        <parent link="base"/><child link="upper"/>
        <origin xyz="0 0 0.5" rpy="0 0 0"/>
        <axis xyz="{axis}"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/>
      </joint>
      <joint name="mount" type="fixed">
        <parent link="upper"/><child link="tool"/>
        <origin xyz="0 0 0.25"/>
      </joint>
    </robot>
"""


def test_mesh_scale_origin_and_primitives(tmp_path):
    mesh = _box_stl(tmp_path / "meshes" / "box.stl")
    path = _write(tmp_path, "arm.urdf", ARM.format(mesh="meshes/box.stl", kind="revolute", axis="0 1 0"))
    del mesh
    arm = read_urdf(path, dtype=np.float64)
    vertices, part = np.asarray(arm.mesh.vertices), np.asarray(arm.mesh.vertex_part)
    assert arm.joint_names == ("shoulder",) and arm.part_names == ("base", "upper")
    assert arm.link_part == {"base": 0, "upper": 1, "tool": 1}
    # base: a 20 x 40 x 60 mm box scaled 2x along its x (40 mm), turned 90° about z, shifted 100 mm in x
    base = vertices[part == 0]
    np.testing.assert_allclose(base.min(0), [80.0, -20.0, -30.0], atol=1e-9)
    np.testing.assert_allclose(base.max(0), [120.0, 20.0, 30.0], atol=1e-9)
    # upper: the 100 x 200 x 300 mm box at 500 mm, and the tool's 10 mm sphere 250 mm above it
    upper = vertices[(part == 1) & (vertices[:, 2] < 700)]
    np.testing.assert_allclose(upper.min(0), [-50.0, -100.0, 350.0], atol=1e-9)
    tool = vertices[(part == 1) & (vertices[:, 2] > 700)]
    np.testing.assert_allclose(np.linalg.norm(tool - [0.0, 0.0, 750.0], axis=1), 10.0, atol=1e-9)
    np.testing.assert_allclose(arm.model.joint_twists[0], [-500.0, 0.0, 0.0, 0.0, 1.0, 0.0], atol=1e-12)
    collision = read_urdf(path, geometry="collision", dtype=np.float64)
    np.testing.assert_allclose(np.ptp(np.asarray(collision.mesh.vertices), axis=0), [100.0, 100.0, 200.0], atol=1e-9)
    # a mirroring scale keeps the surface outward (signed volume > 0)
    mirrored = read_urdf(
        _write(
            tmp_path,
            "mirror.urdf",
            ARM.format(mesh="meshes/box.stl", kind="revolute", axis="0 1 0").replace('scale="2 1 1"', 'scale="-2 1 1"'),
        ),
        dtype=np.float64,
    )
    base = np.asarray(mirrored.mesh.faces)[np.asarray(mirrored.mesh.face_part) == 0]
    tm = trimesh.Trimesh(np.asarray(mirrored.mesh.vertices), base, process=False)
    assert tm.volume > 0


def test_prismatic_and_continuous_joints(tmp_path):
    _box_stl(tmp_path / "box.stl")
    prismatic = read_urdf(_write(tmp_path, "p.urdf", ARM.format(mesh="box.stl", kind="prismatic", axis="0 0 2")))
    assert prismatic.joint_types == ("prismatic",)
    np.testing.assert_allclose(prismatic.lower, [-1000.0]) and np.testing.assert_allclose(
        prismatic.joint_scale, [1000.0]
    )
    poses = prismatic.link_poses(prismatic.joint_vector({"shoulder": 0.1}))
    np.testing.assert_allclose(poses["tool"][:3, 3], [0.0, 0.0, 850.0], atol=1e-3)  # 500 + 100 + 250 mm
    continuous = read_urdf(_write(tmp_path, "c.urdf", ARM.format(mesh="box.stl", kind="continuous", axis="1 0 0")))
    assert continuous.joint_types == ("continuous",) and np.isinf(continuous.lower[0]) and np.isinf(continuous.upper[0])


def test_package_paths(tmp_path):
    _box_stl(tmp_path / "ros" / "my_robot" / "meshes" / "box.stl")
    text = ARM.format(mesh="package://my_robot/meshes/box.stl", kind="revolute", axis="0 1 0")
    # resolved against an ancestor of the URDF (the package's own folder, or the folder holding it)
    inside = read_urdf(_write(tmp_path, "ros/my_robot/urdf/arm.urdf", text))
    assert inside.mesh.num_faces == 12 + 12 + 320
    # or against a search folder
    elsewhere = _write(tmp_path, "other/arm.urdf", text)
    with pytest.raises(ValueError, match=r"link 'base', visual 0: mesh file 'package://my_robot/meshes/box.stl'"):
        read_urdf(elsewhere)
    assert read_urdf(elsewhere, package_dirs=[tmp_path / "ros"]).mesh.num_faces == inside.mesh.num_faces


# ------------------------------------------------------------------------------ bad input

TWO_LINKS = """\
    <robot name="bad">
      <link name="a"><visual><geometry><box size="0.1 0.1 0.1"/></geometry></visual></link>
      <link name="b"/>
      <link name="c"/>
      {joints}
    </robot>
"""


def _joint(name, parent, child, kind="revolute", axis="0 0 1"):
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<axis xyz="{axis}"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
    )


@pytest.mark.parametrize(
    ("joints", "message"),
    [
        ([("j1", "a", "b"), ("j2", "b", "c"), ("j3", "c", "b")], r"link 'b' has two parents \(joints 'j1' and 'j3'\)"),
        ([("j1", "a", "b"), ("j2", "b", "a"), ("j3", "b", "c")], "no root link .* cycle"),
        ([("j1", "a", "b"), ("j2", "c", "c")], r"links \['c'\] are not reachable from root 'a'.*cycle"),
        ([("j1", "a", "b")], r"several root links \['a', 'c'\]"),
        ([("j1", "a", "b", "ball"), ("j2", "b", "c")], "joint 'j1' has unknown type 'ball'"),
        ([("j1", "a", "b", "floating"), ("j2", "b", "c")], "joint 'j1' has unsupported type 'floating'"),
        ([("j1", "a", "b", "revolute", "0 0 0"), ("j2", "b", "c")], r"joint 'j1' has a zero or malformed <axis"),
        ([("j1", "a", "b"), ("j2", "b", "d")], "joint 'j2' names child link 'd', which is not defined"),
    ],
)
def test_bad_structure(tmp_path, joints, message):
    path = _write(tmp_path, "bad.urdf", TWO_LINKS.format(joints="\n".join(_joint(*j) for j in joints)))
    with pytest.raises(ValueError, match=message) as error:
        read_urdf(path)
    assert "bad.urdf" in str(error.value)


def test_bad_files(tmp_path):
    missing = _write(tmp_path, "missing.urdf", ARM.format(mesh="meshes/nothing.stl", kind="revolute", axis="0 0 1"))
    with pytest.raises(
        ValueError, match=r"missing.urdf: link 'base', visual 0: mesh file 'meshes/nothing.stl' not found"
    ):
        read_urdf(missing)
    _write(tmp_path, "empty.stl", "")
    empty = _write(tmp_path, "empty.urdf", ARM.format(mesh="empty.stl", kind="revolute", axis="0 0 1"))
    with pytest.raises(ValueError, match=r"empty.urdf: link 'base', visual 0: .*empty.stl: mesh file is empty"):
        read_urdf(empty)
    broken = _write(tmp_path, "broken.urdf", "<robot name='x'><link name='a'></robot>")
    with pytest.raises(ValueError, match="broken.urdf: cannot parse URDF"):
        read_urdf(broken)
    with pytest.raises(ValueError, match="nowhere.urdf: URDF file not found"):
        read_urdf(tmp_path / "nowhere.urdf")
    limits = _write(
        tmp_path,
        "limits.urdf",
        TWO_LINKS.format(
            joints=_joint("j1", "a", "b").replace('lower="-1" upper="1"', 'lower="1" upper="-1"')
            + _joint("j2", "b", "c")
        ),
    )
    with pytest.raises(ValueError, match=r"joint 'j1': <limit> lower 1.0 > upper -1.0"):
        read_urdf(limits)
    mimic = _write(
        tmp_path,
        "mimic.urdf",
        TWO_LINKS.format(
            joints=_joint("j1", "a", "b").replace("</joint>", '<mimic joint="j9"/></joint>') + _joint("j2", "b", "c")
        ),
    )
    with pytest.raises(ValueError, match="joint 'j1' mimics 'j9', which is not a movable joint"):
        read_urdf(mimic)
    _box_stl(tmp_path / "box.stl")
    good = read_urdf(_write(tmp_path, "good.urdf", ARM.format(mesh="box.stl", kind="revolute", axis="0 0 1")))
    with pytest.raises(ValueError, match="units must be"):
        good.joint_vector({}, units="degrees")
    with pytest.raises(TypeError, match="model_description"):
        write_urdf("not a model", tmp_path / "x.urdf")
