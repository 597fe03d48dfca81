"""A rigid link on a rotational spring under a dead load, posed through the rig's real drivers in Blender:
the link turns to the angle θ of k θ = F L cos θ (the load keeps its direction while the moment arm
shortens), not to the linear spring's F L / k."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import evaluated_positions

L, K = 2.0, 5.0          # link length, spring stiffness (moment per radian)


def _rod():
    """A box rod from the hinge at the origin to y = L (its tip vertex first), 8 vertices, 12 triangles."""
    v = np.array([[x, y, z] for y in (L, 0.0) for x in (-0.1, 0.1) for z in (-0.1, 0.1)])
    v = np.vstack([[0.0, L, 0.0], v])
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    # the tip vertex sits in the middle of the top face: split that face's triangles into a fan
    faces = np.vstack([faces[2:], [[0, 1, 2], [0, 2, 4], [0, 4, 3], [0, 3, 1]]])
    return v, faces


def _hinge_greens(v, probe):
    """G of the linearised hinge: a unit load e_d at the tip turns the rod by ω = (r × e_d)/K about
    the origin, r = (0, L, 0); each vertex moves by ω × x."""
    r = np.array([0.0, L, 0.0])
    G = np.zeros((3 * len(v), 3))
    for d in range(3):
        w = np.cross(r, np.eye(3)[d]) / K
        G[:, d] = np.cross(w, v).ravel()
    return G


def _result(pkg, v, faces, probe):
    """The fit of the hinge's scan: one grounded link, κ of the spring, and the residual that makes each
    probe field (linear: G p̂ e_c) exact at the probe pose, δ_c = R_cᵀ (x0 + G p̂ e_c) − x0."""
    FR = pkg.result.FitResult
    n, kappa = len(v), np.zeros((1, 6, 3))
    kappa[0, 0, 2] = L / K           # θ_x from a load along z: (r × F)_x = L F_z
    kappa[0, 2, 0] = -L / K          # θ_z from a load along x: (r × F)_z = −L F_x
    P = 3
    angles = np.transpose(kappa[:, :3] * probe, (2, 0, 1))
    from scipy.spatial.transform import Rotation
    rot = Rotation.from_euler("xyz", angles.reshape(-1, 3)).as_matrix().reshape(P, 1, 3, 3)
    return FR(face_labels=np.zeros(len(faces), int), parents=np.array([-1]), joints=np.zeros((1, 3)),
              joint_errors=np.zeros(1), heads=np.zeros((1, 3)), tails=np.array([[0.0, L, 0.0]]),
              frames=np.eye(3)[None], grounded=np.array([True]), weights=np.ones((n, 1)), rotations=rot,
              translations=np.zeros((P, 1, 3)), angles=angles, locations=np.zeros((P, 1, 3)),
              residual=np.einsum("pji,pnj->pni", rot[:, 0], v + probe * _hinge_greens(v, probe).T.reshape(P, n, 3)) - v, link_residuals=np.zeros(1), rms_articulation=0.0, rms_total=0.0,
              articulation_error_percent=0.0, kappa=kappa, load_vertices=np.array([0]), probe_load=probe)


def _tip(obj):
    """The evaluated (posed) position of the link's tip, vertex 0."""
    return evaluated_positions(obj)[0]


def test_a_rigid_link_on_a_rotational_spring_turns_as_a_dead_load_turns_it(clean_scene, pkg, tmp_path):
    assert not bpy.context.preferences.filepaths.use_scripts_auto_execute
    v, faces = _rod()
    probe = 0.1 * K / L                       # turns the rod by 0.1 rad to first order
    scan = pkg.scan.Scan(v, faces, greens=_hinge_greens(v, probe), load_vertices=np.array([0]),
                          support_vertices=np.arange(5, 9), probe_load=probe)
    path = str(tmp_path / "rod.npz")
    pkg.files.write_scan(path, scan)
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    obj = bpy.context.view_layer.objects.active
    pkg.rig.build_rig(bpy.context, obj, _result(pkg, v, faces, probe), np.arange(len(faces)), "greens")
    for fc in list(obj.artdef.rig.animation_data.drivers) + list(obj.data.shape_keys.animation_data.drivers):
        assert fc.driver.is_valid and (fc.driver.type != 'SCRIPTED' or fc.driver.is_simple_expression)
    emp = bpy.data.objects["artdef_load_0"]
    emp.animation_data_clear()
    for theta in (0.3, 0.6, 0.9):
        F = K * theta / (L * np.cos(theta))   # the load whose spring balance k θ = F L cos θ has this θ
        for axis, sign in ((2, 1.0), (0, -1.0)):
            emp.location = F * np.eye(3)[axis]
            tip = _tip(obj)
            # the tip swings on a circle of radius L towards the load: its angle is the link's
            got = np.arctan2(tip[axis], tip[1])
            assert np.linalg.norm(tip) == pytest.approx(L, rel=1e-4)
            assert abs(got - theta) <= 0.02 * theta, (theta, axis, got)
            assert abs(F * L / K - theta) >= 0.04 * theta       # the linear spring would be this far off
    emp.location = (0.0, 0.0, 0.0)
    np.testing.assert_allclose(_tip(obj), [0.0, L, 0.0], atol=1e-6)
