"""The objects a heap is made of: corpus meshes loaded once per process, with what pybullet
and the grasp checks need of each (computed once per object id, then shared by every heap).

A library maps object id -> ``HeapObject``.  ``default_library()`` reads the default corpus
(``pipeline.build.corpus``) lazily; tests build a library of hand-made models with ``add``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import fcl
import numpy as np
import trimesh

from ..build.corpus import Corpus, load_corpus
from ..model.config import MeshConfig
from ..model.mesh import ObjectModel, load_mesh


@dataclass
class HeapObject:
    """One object, ready for heaps.

    model : the mesh (object frame, m), hull, mass (kg), centre of mass (object frame, m)
    hull_link : (V, 3) float, m, hull vertices in the link frame (principal axes at the centre of mass)
    inertia : (3,) float, kg m^2, principal moments of the uniform-density solid scaled to the mass
    link_from_object : (3, 3) float, rotation object frame -> link frame
    radius : float, m, largest distance of a hull vertex from the centre of mass
    """

    model: ObjectModel
    hull_link: np.ndarray
    inertia: np.ndarray
    link_from_object: np.ndarray
    radius: float
    _fcl: fcl.CollisionGeometry | None = field(default=None, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def collision_geometry(self) -> fcl.CollisionGeometry:
        """The full mesh as an fcl BVH (object frame), built on first use."""
        if self._fcl is None:
            mesh = self.model.mesh
            model = fcl.BVHModel()
            model.beginModel(len(mesh.vertices), len(mesh.faces))
            model.addSubModel(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int32))
            model.endModel()
            self._fcl = model
        return self._fcl

    @property
    def cache(self) -> dict:
        """Per-object results of the grasp modules (candidates in the object frame), by name."""
        return self._cache


def heap_object(model: ObjectModel) -> HeapObject:
    """Mass properties and the hull in the principal frame (as ``pipeline.studies.pushsim`` does
    for one pushed object: uniform density, scaled to the mass, moved to the model's centre of mass)."""
    solid = model.mesh if model.mesh.is_volume and model.mesh.volume > 0 else model.hull
    scale = model.mass / solid.mass
    offset = model.center_mass - solid.center_mass
    inertia = solid.moment_inertia * scale + model.mass * (np.dot(offset, offset) * np.eye(3) - np.outer(offset, offset))
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:  # a proper rotation: the link frame is right-handed
        axes[:, 2] *= -1
    link_from_object = axes.T
    hull_link = (model.hull.vertices - model.center_mass) @ link_from_object.T
    radius = float(np.linalg.norm(hull_link, axis=1).max())
    return HeapObject(model, hull_link, np.maximum(moments, 1e-12), link_from_object, radius)


class ObjectLibrary:
    """Objects by id, loaded on first use.

    corpus : where ids come from (None: only objects ``add``-ed)
    max_extent : m, objects whose largest side exceeds this are not offered by ``ids``
    """

    def __init__(self, corpus: Corpus | None = None, max_extent: float = np.inf):
        self.corpus = corpus
        self.max_extent = max_extent
        self._specs = {s.object_id: s for s in corpus.specs} if corpus else {}
        self._objects: dict[str, HeapObject] = {}
        self._ids: tuple[str, ...] | None = None

    def add(self, object_id: str, model: ObjectModel) -> HeapObject:
        """Register an in-memory model (tests, hand-made shapes)."""
        self._objects[object_id] = heap_object(model)
        self._ids = None
        return self._objects[object_id]

    def __getitem__(self, object_id: str) -> HeapObject:
        if object_id not in self._objects:
            spec = self._specs.get(object_id)
            if spec is None:
                raise KeyError(f"unknown object id {object_id!r} (not in the corpus)")
            model = load_mesh(Path(spec.path), spec.scale, spec.mass, name=spec.object_id, config=MeshConfig())
            self._objects[object_id] = heap_object(model)
        return self._objects[object_id]

    def ids(self) -> tuple[str, ...]:
        """Ids a heap may draw from, in corpus order (then added ones): those not larger than ``max_extent``."""
        if self._ids is None:
            every = list(self._specs) + [k for k in self._objects if k not in self._specs]
            self._ids = tuple(k for k in every if float(self[k].model.hull.extents.max()) <= self.max_extent)
        return self._ids


_DEFAULT: dict[float, ObjectLibrary] = {}


def default_library(max_extent: float) -> ObjectLibrary:
    """The default corpus's library, one per process (meshes load on first use)."""
    if max_extent not in _DEFAULT:
        corpus = load_corpus("default", MeshConfig().default_mass)
        if corpus.problems:
            first = next(iter(corpus.problems.items()))
            raise RuntimeError(f"default corpus has unusable objects, e.g. {first[0]}: {first[1]}")
        _DEFAULT[max_extent] = ObjectLibrary(corpus, max_extent)
    return _DEFAULT[max_extent]


def box_model(extents: tuple[float, float, float], mass: float = 0.2, name: str = "box") -> ObjectModel:
    """A solid box centred on its frame's origin (for tests and examples).

    extents : (3,) float, m, side lengths along x, y, z
    """
    from ..model.mesh import model_from_mesh

    return model_from_mesh(trimesh.creation.box(extents=extents), mass=mass, name=name)
