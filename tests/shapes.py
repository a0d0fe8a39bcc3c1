"""Test objects with known answers, shared by the geometry tests."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pybullet_data
import trimesh

from pipeline.model.config import PRESETS, Config
from pipeline.model.mesh import load_mesh, model_from_mesh

DATA = pybullet_data.getDataPath()
THESIS = Config.from_toml(PRESETS / "thesis.toml")
"""The thesis's model, friction and noise (`--config thesis`): for tests of the thesis's variants,
and of the push player, which `make logs` plays with them (the default noise is calibrated)."""


def box_object(size=(0.05, 0.08, 0.15), mass=0.25):
    """A box with its base at z = 0; its standing pose is the identity."""
    mesh = trimesh.creation.box(size)
    mesh.apply_translation([0, 0, size[2] / 2])
    return model_from_mesh(mesh, mass=mass, name="box")


def boot_object():
    """A tall block with a thin toe rising at 10 degrees from one bottom edge.

    Standing on the block, a push over the toe's edge is blocked: the toe meets
    the table (10 degrees) before the centre of mass passes the edge (~18 degrees).
    """
    block = trimesh.creation.box([0.04, 0.04, 0.10])
    block.apply_translation([0.02, 0.02, 0.05])
    # Inset in y so no vertex coincides with the block's: both shells stay closed.
    toe = trimesh.creation.box([0.08, 0.036, 0.004])
    toe.apply_translation([0.04, 0.02, 0.002])  # inner bottom edge on x = 0, z = 0
    toe.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-10), [0, 1, 0], [0, 0, 0]))
    toe.apply_translation([0.04, 0, 0])
    return model_from_mesh(trimesh.util.concatenate([block, toe]), mass=0.2, name="boot")


def random_object(index: int):
    """One of pybullet_data's random objects at its URDF scale and mass."""
    return load_mesh(f"{DATA}/random_urdfs/{index:03d}/{index:03d}.obj", scale=0.015, mass=0.1, name=f"random_{index:03d}")


def candidate_pushes(obj, pose, n_contacts, seed):
    """The candidate pushes (``Actions``) of one stable pose from ``n_contacts`` contacts drawn with
    ``seed``, as the dataset job makes them."""
    from pipeline.model.collision import collision_object
    from pipeline.model.config import ContactConfig
    from pipeline.model.contacts import object_contacts, pose_actions

    contacts = ContactConfig(n_contacts=n_contacts)
    points, normals = object_contacts(obj, contacts, seed)
    return pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), pose.transform, contacts)


def pose_with_down(pose_set, down, atol=1e-6):
    """Index of the pose whose object-frame down vector is ``down``."""
    for pose in pose_set.poses:
        if np.allclose(pose.down, down, atol=atol):
            return pose.index
    raise AssertionError(f"no pose with down {down}")


def standing_box():
    """(object, pose set, index of its pose standing on end) for the 0.05 x 0.08 x 0.15 m box."""
    from pipeline.model.poses import stable_poses

    obj = box_object((0.05, 0.08, 0.15))
    pose_set = stable_poses(obj)
    return obj, pose_set, pose_with_down(pose_set, [0, 0, -1])


def overhanging_frustum():
    """(object, pose set, index of the pose on its small face) for a square frustum standing
    upside down: a 4 x 4 cm base, an 8 x 8 cm top 6 cm up, 0.2 kg.  Its top face overhangs every
    base edge by up to 2 cm, so a push down onto it beyond an edge can tip it over that edge."""
    from pipeline.model.poses import stable_poses

    a, b, h = 0.02, 0.04, 0.06
    corners = [[x * a, y * a, 0.0] for x in (-1, 1) for y in (-1, 1)] + [[x * b, y * b, h] for x in (-1, 1) for y in (-1, 1)]
    obj = model_from_mesh(trimesh.convex.convex_hull(np.array(corners)), mass=0.2, name="frustum")
    pose_set = stable_poses(obj)
    return obj, pose_set, pose_with_down(pose_set, [0, 0, -1], atol=1e-3)


def noise_free(variant="corrected", **fields):
    """A noise-free trial of ``variant`` at the thesis's friction means (mu_T 0.43, mu_f 0.98: the
    world the push player plays), the other fields the defaults, then ``fields``.  corrected is
    robust, so every spread is zeroed; no smoothing over neighbouring pushes and no recalibration
    map (MODEL.md C.12, C.7, C.15 and C.19 are tested on their own): each push is judged alone."""
    topple = replace(
        Config().topple,
        variant=variant,
        n_trials=1,
        mu_table_mean=THESIS.topple.mu_table_mean,
        mu_table_std=0.0,
        mu_finger_mean=THESIS.topple.mu_finger_mean,
        mu_finger_std=0.0,
        contact_std=0.0,
        direction_std=0.0,
        rotation_std=0.0,
        smoothing_radius=0.0,
        recalibration_x=(),
        recalibration_y=(),
        down_map=(),
        boosted_map="",
    )
    return replace(topple, **fields)


def stroke_to_apex(height, d=0.04, w=0.08, com_height=0.075):
    """Finger travel (m) that tips the standing box to its apex, pushed horizontally at ``height``
    on a side face w from the far edge (MODEL.md C.10.3): the face turns by theta_a =
    atan(d / com_height) about that edge, and a point finger at that height meets it
    h tan(theta_a) - w (sec(theta_a) - 1) past the contact.  Defaults: across the 8 cm side."""
    apex = np.arctan2(d, com_height)
    return height * np.tan(apex) - w * (1.0 / np.cos(apex) - 1.0)


def faceted_rod(sides=12, radius=0.02, length=0.12, mass=0.1):
    """(object, pose set, index of a pose lying on a facet) for a regular prism of ``sides`` sides lying on its
    side: circumradius ``radius``, its axis along the object's y.  Every facet is the same pose (merged by
    symmetry), so a roll onto the next facet lands where it left: test its trials, not its rows."""
    from pipeline.model.poses import stable_poses

    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sides)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    obj = model_from_mesh(mesh, mass=mass, name=f"rod{sides}")
    pose_set = stable_poses(obj)
    lying = next(p.index for p in pose_set.poses if abs(p.down[1]) < 1e-6)
    return obj, pose_set, lying


def explicit_trials(shape, points, directions, topple, seed=0):
    """The engine's trials of explicit pushes on ``shape`` ((object, pose set, pose index)), drawn as
    ``evaluate_pose`` draws them (``topple.pose_noise``), and the pose's edges: (object, trials, edges).
    points, directions : (n, 3), pose frame."""
    from pipeline.model.contacts import explicit_actions
    from pipeline.model.edges import edge_geometry
    from pipeline.model.rng import stream
    from pipeline.model.topple import noisy_trials, pose_noise
    from schema.frames import transform_points

    obj, pose_set, index = shape
    pose = pose_set.poses[index]
    actions = explicit_actions(obj, pose.transform, np.asarray(points, float), np.asarray(directions, float))
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    noise = pose_noise(stream(seed, obj.name, index, "trials"), len(actions.status), len(actions.status), topple)
    trials = noisy_trials(obj, pose.transform, center_mass, actions.points, actions.normals, actions.directions, noise, topple)
    return obj, trials, edge_geometry(pose.base_edges, center_mass)
