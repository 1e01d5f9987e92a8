"""The robot catalogue (configs/robots/catalogue/) against independent computations of its sources.

Each arm's forward kinematics (`frames.robots.load`) is compared at random joint vectors with
the vendor's own description computed another way: the vendor's URDF joints written out below
as a URDF and evaluated by yourdfpy's scene graph (a kinematics engine that is not ours), or the
vendor's DH table evaluated with the DH matrix written out here. Positions to 1e-9 m, and the
flange's orientation through a 0.1 m tool offset along its z (how a TCP offset is carried).
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import chain_from_urdf, load_robot

PI, H = np.pi, np.pi / 2
RNG_Q = np.random.default_rng(21).uniform(-2.5, 2.5, (6, 7))


def _urdf_text(joints, name="arm"):
    """URDF of a chain: joints are (name, type, parent, child, xyz, rpy, axis)."""
    links = {j[2] for j in joints} | {j[3] for j in joints}
    out = [f'<robot name="{name}">'] + [f'<link name="{lk}"/>' for lk in sorted(links)]
    def v(x):
        return " ".join(map(repr, map(float, x)))

    for nm, kind, parent, child, xyz, rpy, axis in joints:
        out.append(f'<joint name="{nm}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
                   f'<origin xyz="{v(xyz)}" rpy="{v(rpy)}"/>'
                   + (f'<axis xyz="{v(axis)}"/>' if axis is not None else "")
                   + (' <limit lower="-6.3" upper="6.3" effort="1" velocity="1"/>' if kind == "revolute" else "")
                   + "</joint>")
    return "\n".join(out + ["</robot>"])


def _yourdfpy_fk(tmp_path, joints, root, tip, q):
    """Poses (n, 4, 4) of `tip` in `root` by yourdfpy's scene graph."""
    import yourdfpy

    f = tmp_path / "vendor.urdf"
    f.write_text(_urdf_text(joints))
    u = yourdfpy.URDF.load(str(f), build_scene_graph=True, load_meshes=False, load_collision_meshes=False)
    names = u.actuated_joint_names
    out = []
    for row in q:
        u.update_cfg(dict(zip(names, row[:len(names)])))
        out.append(u.get_transform(frame_to=tip, frame_from=root))
    return np.array(out)


def _check(chain, T_ref):
    q = RNG_Q[:len(T_ref), :chain.dof]
    np.testing.assert_allclose(chain.fk(q), T_ref[:, :3, 3], rtol=0, atol=1e-9)
    # the flange's axes: a tool 0.1 m along the flange's z lands where the vendor's z points
    tool = chain.with_tool([0.0, 0.0, 0.1]).fk(q)
    np.testing.assert_allclose(tool, T_ref[:, :3, 3] + 0.1 * T_ref[:, :3, 2], rtol=0, atol=1e-9)


def _revolute_chain(rows, tool_xyz, tool_rpy, base_xyz=(0, 0, 0)):
    """Vendor URDF rows (xyz, rpy, axis) as joints j1..jn from `root` (placed at base_xyz in it)
    through base_link, and the flange `tool0`."""
    joints = [("base_fixed", "fixed", "root", "l0", base_xyz, (0, 0, 0), None)]
    for i, (xyz, rpy, axis) in enumerate(rows):
        joints.append((f"j{i + 1}", "revolute", f"l{i}", f"l{i + 1}", xyz, rpy, axis))
    joints.append(("flange", "fixed", f"l{len(rows)}", "tool0", tool_xyz, tool_rpy, None))
    return joints


# --- Universal Robots: default_kinematics.yaml (Universal_Robots_ROS2_Description 2.4.5) as URDF origins
UR_KINEMATICS = {  # shoulder, upper_arm, forearm, wrist_1, wrist_2, wrist_3: x y z roll pitch yaw
    "ur3": [(0, 0, 0.1519, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.24365, 0, 0, 0, 0, 0),
            (-0.21325, 0, 0.11235, 0, 0, 0), (0, -0.08535, -1.750557762378351e-11, 1.570796327, 0, 0),
            (0, 0.0819, -1.679797079540562e-11, 1.570796326589793, PI, PI)],
    "ur5": [(0, 0, 0.089159, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.425, 0, 0, 0, 0, 0),
            (-0.39225, 0, 0.10915, 0, 0, 0), (0, -0.09465, -1.941303950897609e-11, 1.570796327, 0, 0),
            (0, 0.0823, -1.688001216681175e-11, 1.570796326589793, PI, PI)],
    "ur10": [(0, 0, 0.1273, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.612, 0, 0, 0, 0, 0),
             (-0.5723, 0, 0.163941, 0, 0, 0), (0, -0.1157, -2.373046667922381e-11, 1.570796327, 0, 0),
             (0, 0.0922, -1.891053610911353e-11, 1.570796326589793, PI, PI)],
    "ur3e": [(0, 0, 0.15185, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.24355, 0, 0, 0, 0, 0),
             (-0.2132, 0, 0.13105, 0, 0, 0), (0, -0.08535, -1.750557762378351e-11, 1.570796327, 0, 0),
             (0, 0.0921, -1.8890025766262e-11, 1.570796326589793, PI, PI)],
    "ur5e": [(0, 0, 0.1625, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.425, 0, 0, 0, 0, 0),
             (-0.3922, 0, 0.1333, 0, 0, 0), (0, -0.0997, -2.044881182297852e-11, 1.570796327, 0, 0),
             (0, 0.0996, -2.042830148012698e-11, 1.570796326589793, PI, PI)],
    "ur10e": [(0, 0, 0.1807, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.6127, 0, 0, 0, 0, 0),
              (-0.57155, 0, 0.17415, 0, 0, 0), (0, -0.11985, -2.458164590756244e-11, 1.570796327, 0, 0),
              (0, 0.11655, -2.390480459346185e-11, 1.570796326589793, PI, PI)],
    "ur16e": [(0, 0, 0.1807, 0, 0, 0), (0, 0, 0, 1.570796327, 0, 0), (-0.4784, 0, 0, 0, 0, 0),
              (-0.36, 0, 0.17415, 0, 0, 0), (0, -0.11985, -2.458164590756244e-11, 1.570796327, 0, 0),
              (0, 0.11655, -2.390480459346185e-11, 1.570796326589793, PI, PI)],
}


@pytest.mark.parametrize("name", sorted(UR_KINEMATICS))
def test_universal_robots_dh_matches_their_ros_description(name, tmp_path):
    rows = [((x, y, z), (r, p, yw), (0, 0, 1)) for x, y, z, r, p, yw in UR_KINEMATICS[name]]
    # ur_macro.xacro: wrist_3_link -> flange (0, -pi/2, -pi/2) -> tool0 (pi/2, 0, pi/2), composed here
    # by the URDF engine; the controller's Base is base_link_inertia (the chain's root here).
    joints = _revolute_chain(rows, (0, 0, 0), (0, -H, -H))
    joints.append(("flange-tool0", "fixed", "tool0", "tool0_ros", (0, 0, 0), (H, 0, H), None))
    T = _yourdfpy_fk(tmp_path, joints, "root", "tool0_ros", RNG_Q)
    _check(robots.load(name), T)


def test_franka_panda_craig_table_matches_its_urdf(tmp_path):
    rows = [((0, 0, 0.333), (0, 0, 0)), ((0, 0, 0), (-H, 0, 0)), ((0, -0.316, 0), (H, 0, 0)),
            ((0.0825, 0, 0), (H, 0, 0)), ((-0.0825, 0.384, 0), (-H, 0, 0)), ((0, 0, 0), (H, 0, 0)),
            ((0.088, 0, 0), (H, 0, 0))]  # franka_arm.xacro joint1..joint7, then joint8 (link8) 0.107 along z
    T = _yourdfpy_fk(tmp_path, _revolute_chain([(x, r, (0, 0, 1)) for x, r in rows], (0, 0, 0.107), (0, 0, 0)),
                     "root", "tool0", RNG_Q)
    chain = robots.load("panda")
    assert chain.dof == 7
    _check(chain, T)


IIWA = {  # lbr_fri_ros2_stack <arm>_description.xacro: A1..A7 origins and axes, then joint_ee 0.035
    "iiwa7": [((0, 0, 0.1475), (0, 0, 1)), ((0, -0.0105, 0.1925), (0, 1, 0)), ((0, 0.0105, 0.2075), (0, 0, 1)),
              ((0, 0.0105, 0.1925), (0, -1, 0)), ((0, -0.0105, 0.2075), (0, 0, 1)),
              ((0, -0.0707, 0.1925), (0, 1, 0)), ((0, 0.0707, 0.091), (0, 0, 1))],
    "iiwa14": [((0, 0, 0.1475), (0, 0, 1)), ((0, -0.01, 0.2125), (0, 1, 0)), ((0, 0.01, 0.228), (0, 0, 1)),
               ((0, 0.0105, 0.192), (0, -1, 0)), ((0, -0.0105, 0.2075), (0, 0, 1)),
               ((0, -0.0707, 0.1925), (0, 1, 0)), ((0, 0.0707, 0.091), (0, 0, 1))],
}


@pytest.mark.parametrize("name", sorted(IIWA))
def test_kuka_iiwa_matches_its_urdf(name, tmp_path):
    rows = [(x, (0, 0, 0), a) for x, a in IIWA[name]]
    T = _yourdfpy_fk(tmp_path, _revolute_chain(rows, (0, 0, 0.035), (0, 0, 0)), "root", "tool0", RNG_Q)
    _check(robots.load(name), T)


def test_iiwa14_axes_agree_with_kukas_own_description(tmp_path):
    """KUKA's description (kroshu kuka_robot_descriptions, lbr_iiwa14_r820_macro.xacro) places the
    wrist (A6) where the catalogue's does; its flange sits 0.026 m further out (another flange)."""
    kuka = [((0, 0, 0.1575), (0, 0, 1)), ((0, 0, 0.2025), (0, 1, 0)), ((0, 0, 0.2045), (0, 0, 1)),
            ((0, 0, 0.2155), (0, -1, 0)), ((0, 0, 0.1845), (0, 0, 1)), ((0, 0, 0.2155), (0, 1, 0)),
            ((0, 0, 0.081), (0, 0, 1))]
    T = _yourdfpy_fk(tmp_path, _revolute_chain([(x, (0, 0, 0), a) for x, a in kuka], (0, 0, 0.071), (0, 0, 0)),
                     "root", "tool0", RNG_Q)
    chain = robots.load("iiwa14")
    q = RNG_Q[:, :7]
    ours = chain.frames(q)[2]
    np.testing.assert_allclose(ours[:, :3, :3], T[:, :3, :3], atol=1e-12)  # the same flange axes
    # the wrist point (A6's axis on the flange's line) 0.126 m behind our flange, 0.152 m behind KUKA's
    np.testing.assert_allclose(ours[:, :3, 3] - 0.126 * ours[:, :3, 2], T[:, :3, 3] - 0.152 * T[:, :3, 2],
                               rtol=0, atol=1e-9)


def test_barrett_wam_matches_libbarretts_dh_matrix():
    """libbarrett wam7w.conf (alpha_pi, a, d per moving link; toolplate zero) through the link
    matrix of libbarrett's src/cdlbt/kinematics.c, written out here."""
    table = [(-0.5, 0, 0), (0.5, 0, 0), (-0.5, 0.045, 0.55), (0.5, -0.045, 0), (-0.5, 0, 0.3), (0.5, 0, 0),
             (0, 0, 0.0609)]
    T_ref = []
    for q in RNG_Q:
        T = np.eye(4)
        for (alpha_pi, a, d), th in zip(table, q):
            al = alpha_pi * np.pi
            ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
            T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                              [0, sa, ca, d], [0, 0, 0, 1]])
        T_ref.append(T)
    chain = robots.load("wam")
    assert chain.dof == 7
    _check(chain, np.array(T_ref))


YASKAWA = {  # motoman_<arm>_support/urdf/<arm>_macro.xacro: joint origins, axes, tool0; 'base' above base_link
    "hc10": ([((0, 0, 0.275), (0, 0, 1)), ((0, 0, 0), (0, 1, 0)), ((0, 0, 0.7), (0, -1, 0)),
              ((0, 0, -0.5), (0, 0, 1)), ((0, 0.162, 0), (0, -1, 0)), ((0, 0, 0), (0, 0, 1))],
             (0, 0, -0.13), (PI, 0, 0), 0.275),
    "hc20": ([((0, 0, 0.38), (0, 0, 1)), ((0, 0, 0), (0, 1, 0)), ((0, 0, 0.82), (0, -1, 0)),
              ((0.88, 0, 0), (-1, 0, 0)), ((0, 0, 0), (0, -1, 0)), ((0, 0, 0), (-1, 0, 0))],
             (0.2, 0, 0), (PI, -H, 0), 0.38),
}


@pytest.mark.parametrize("name", sorted(YASKAWA))
def test_yaskawa_matches_its_urdf_in_the_controllers_frame(name, tmp_path):
    rows, fxyz, frpy, z_base = YASKAWA[name]
    joints = _revolute_chain([(x, (0, 0, 0), a) for x, a in rows], fxyz, frpy)
    joints.append(("base_link-base", "fixed", "l0", "base", (0, 0, z_base), (0, 0, 0), None))
    T_base = _yourdfpy_fk(tmp_path, joints, "base", "tool0", RNG_Q)  # in the robot frame 'base'
    _check(robots.load(name), T_base)


DOOSAN = {"m0609": (0.006, 0.411, 0.368), "m0617": (0.0345, 0.845, 0.734), "m1013": (0.0345, 0.62, 0.559),
          "m1509": (0.0345, 0.411, 0.368)}


@pytest.mark.parametrize("name", sorted(DOOSAN))
def test_doosan_matches_its_urdf(name, tmp_path):
    y2, l3, l4 = DOOSAN[name]  # dsr_description2/urdf/<arm>.white.urdf, pi/2 written 1.571 there
    rows = [((0, 0, 0.1525), (0, 0, 0)), ((0, y2, 0), (0, -1.571, -1.571)), ((l3, 0, 0), (0, 0, 1.571)),
            ((0, -l4, 0), (1.571, 0, 0)), ((0, 0, 0), (-1.571, 0, 0)), ((0, -0.121, 0), (1.571, 0, 0))]
    T = _yourdfpy_fk(tmp_path, _revolute_chain([(x, r, (0, 0, 1)) for x, r in rows], (0, 0, 0), (0, 0, 0)),
                     "root", "tool0", RNG_Q)
    _check(robots.load(name), T)


ABB = {"crb15000_5_95": (0.265, 0.444, 0.47), "crb15000_12_127": (0.338, 0.707, 0.534)}


@pytest.mark.parametrize("name", sorted(ABB))
def test_abb_gofa_matches_its_urdf(name, tmp_path):
    z1, l3, l5 = ABB[name]  # abb_crb15000_support/urdf/<arm>_macro.xacro; tool0 = flange turned pi/2 about y
    rows = [((0, 0, z1), (0, 0, 1)), ((0, 0, 0), (0, 1, 0)), ((0, 0, l3), (0, 1, 0)), ((0, 0, 0.11), (1, 0, 0)),
            ((l5, 0, 0), (0, 1, 0)), ((0.101, 0, 0.08), (1, 0, 0))]
    T = _yourdfpy_fk(tmp_path, _revolute_chain([(x, (0, 0, 0), a) for x, a in rows], (0, 0, 0), (0, H, 0)),
                     "root", "tool0", RNG_Q)
    _check(robots.load(name), T)


def test_every_catalogue_arm_is_tested_and_cites_a_versioned_source():
    tested = set(UR_KINEMATICS) | set(IIWA) | set(YASKAWA) | set(DOOSAN) | set(ABB) | {"panda", "wam"}
    assert set(robots.names()) == tested
    for e in robots.catalogue():
        assert e.vendor and e.sources and e.dof in (6, 7)
        for s in e.sources:
            assert s["url"].startswith("https://") and s["version"]
    assert {e.name: e.dof for e in robots.catalogue()}["panda"] == 7


def test_the_cobot_urdf_gives_the_chain_the_hand_written_parser_gave():
    """sim/assets/cobot.urdf through yourdfpy: the joint frames and tool the project's own
    ElementTree parser produced (numbers written out here), bit for bit."""
    chain = load_robot(robots.CATALOGUE.parent / "cobot_hc20_like.yaml")
    xyz = [(0, 0, 0.25), (0.15, 0, 0.13), (0, 0, 0.82), (0, 0, 0.15), (0.70, 0, 0), (0.12, 0, 0)]
    axes = [(0, 0, 1), (0, 1, 0), (0, 1, 0), (1, 0, 0), (0, 1, 0), (1, 0, 0)]
    for T, p, a, ax in zip(chain.origins, xyz, axes, chain.axes):
        assert np.array_equal(T[:3, :3], np.eye(3)) and np.array_equal(T[:3, 3], p) and np.array_equal(ax, a)
    assert np.array_equal(chain.tool[:3, 3], [0.10, 0, 0]) and chain.tool_given and chain.name == "cobot_hc20_like"


def test_references_name_a_catalogue_arm_a_config_or_a_urdf_with_its_link_and_a_tool(tmp_path):
    assert robots.reference("ur5e") == "ur5e"
    assert robots.reference(robots.CATALOGUE.parent / "ur10.yaml") == "robots/ur10.yaml"
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(_urdf_text([("a", "revolute", "base", "l1", (0, 0, 0.3), (0, 0, 0), (0, 0, 1)),
                                ("b", "revolute", "l1", "l2", (0.4, 0, 0), (0, 0, 0), (0, 1, 0)),
                                ("c", "fixed", "l2", "tool0", (0.1, 0, 0), (0, 0, 0), None),
                                ("d", "fixed", "l1", "camera", (0, 0.2, 0), (0, 0, 0), None)]))
    ref = robots.resolve(f"{urdf}#tool0?tool_mm=0,0,50")
    assert ref.text == f"{urdf}#tool0?tool_mm=0.000000,0.000000,50.000000"
    chain = robots.load(ref.text)
    np.testing.assert_allclose(chain.fk(np.zeros((1, 2)))[0], [0.5, 0, 0.35], atol=1e-15)
    assert chain.tool_given and not robots.load(str(urdf)).tool_given
    assert chain_from_urdf(urdf, "camera").dof == 1
    with pytest.raises(ConfigError, match="ur6.*ur5e.*dt robots"):
        robots.resolve("ur6")
    with pytest.raises(DataError, match="no such file"):
        robots.resolve("nowhere/arm.urdf")
    with pytest.raises(ConfigError, match="tool_mm"):
        robots.resolve("ur5e?tool_mm=1,2")


def test_a_config_adds_a_tool_and_base_to_a_catalogue_arm(tmp_path):
    (tmp_path / "cell.yaml").write_text("name: my_ur5e\narm: ur5e\ntool_xyz_m: [0, 0, 0.1]\n"
                                        "base_rpy_rad: [0, 0, 3.141592653589793]\n")
    mine, arm = load_robot(tmp_path / "cell.yaml"), robots.load("ur5e")
    q = RNG_Q[:, :6]
    Rz = Rotation.from_euler("z", np.pi).as_matrix()
    np.testing.assert_allclose(mine.fk(q), arm.with_tool([0, 0, 0.1]).fk(q) @ Rz.T, atol=1e-12)
    assert mine.tool_given and mine.name == "my_ur5e"


@pytest.mark.parametrize("text, key", [
    ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>'
     '</joint></robot>', "joint 'j'/child"),
    ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>'
     '<child link="b"/><axis/></joint></robot>', "joint 'j'/axis@xyz"),
    ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="prismatic"><parent link="a"/>'
     '<child link="b"/><axis xyz="0 0 1"/></joint></robot>', "joint 'j'@type"),
    ('<robot name="r"><link name="a"/><link', "<file>"),
])
def test_a_bad_urdf_is_a_config_error_naming_the_element(tmp_path, text, key):
    f = tmp_path / "bad.urdf"
    f.write_text(text)
    with pytest.raises(ConfigError) as ei:
        chain_from_urdf(f)
    assert ei.value.key == key and ei.value.file == str(f)
