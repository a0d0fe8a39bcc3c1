"""Pictures of what the model says about one object (thesis figures 4.5 and 4.6).

    toppledb figures MESH [--scale S] [--mass KG] [--pose N] [--out DIR]

- ``pushes_<pose>.png`` (figure 4.5): the object resting in the pose, its candidate
  contacts coloured by P(topple), and the pose the best push most likely leads to;
- ``graph.png`` (figure 4.6): the topple graph: one node per stable pose coloured by
  V_s, an arrow x -> x' labelled with the largest P(x' | x, u) over the pushes u;
- ``object.glb``: an interactive 3D view (the mesh in the pose and the contacts as
  coloured points), for any glTF viewer.

Everything is computed for the mesh on the spot with ``pipeline.model.evaluation.evaluate_object``
(no dataset needed); the defaults are light (200 pushes, 20 trials) so that it takes
seconds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

NODE_EDGE_COLOR = "#ff00ff"
"""Every pose node's outline, a colour used nowhere else (tests count the nodes by it)."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def pushes_figure(obj, result, pose: int, path: str | Path) -> dict:
    """Figure 4.5: the object in ``pose`` with its candidate contacts coloured by P(topple).
    Returns what was drawn: {"contacts": n, "best": action or None}."""
    from schema.frames import transform_points
    from schema.vocabulary import STATUS_NAMES

    plt = _pyplot()
    stable = result.poses[pose]
    vertices = transform_points(stable.transform, np.asarray(obj.mesh.vertices))
    actions, table = result.actions[pose], result.topple[pose]
    ok = np.array([STATUS_NAMES[s] == "ok" for s in actions.status])
    p_topple = np.nan_to_num(np.asarray(table.p_topple, dtype=float))
    fig = plt.figure(figsize=(6, 5), dpi=100)
    ax = fig.add_subplot(projection="3d")
    ax.plot_trisurf(vertices[:, 0], vertices[:, 1], vertices[:, 2], triangles=np.asarray(obj.mesh.faces),
                    color="0.85", alpha=0.35, linewidth=0)
    points = actions.points[ok]
    scatter = ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=p_topple[ok], cmap="viridis", vmin=0, vmax=1, s=12)
    fig.colorbar(scatter, ax=ax, shrink=0.7, label="P(topple)")
    best = int(np.argmax(np.where(ok, p_topple, -1))) if ok.any() else None
    title = f"{result.object_id}, pose {pose}: {int(ok.sum())} executable pushes"
    if best is not None:
        ax.scatter(*actions.points[best], color="red", s=60, marker="*")
        outcome = np.nan_to_num(np.asarray(table.next_pose[best], dtype=float))
        title += f"\nbest push (red): P(topple) {p_topple[best]:.2f}, most likely next pose {int(np.argmax(outcome))}"
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)"), ax.set_zlabel("z (m)")
    fig.savefig(path)
    plt.close(fig)
    return {"contacts": int(ok.sum()), "best": best}


def topple_edges(result) -> dict[tuple[int, int], float]:
    """(x, x') -> the largest P(x' | x, u) over ``ok`` pushes u, for x' != x."""
    edges = {}
    for x, table in enumerate(result.topple):
        probabilities = np.nan_to_num(np.asarray(table.next_pose, dtype=float))
        if probabilities.size == 0:
            continue
        best = probabilities.max(axis=0)
        for target in np.flatnonzero(best > 0):
            if int(target) != x:
                edges[(x, int(target))] = float(best[target])
    return edges


def edge_label(probability: float) -> str:
    """An arrow's label: two decimals, and "<0.01" for the smoothed rows' small shares, which two
    decimals would show as an arrow of probability 0.00."""
    return f"{probability:.2f}" if probability >= 0.005 else "<0.01"


def graph_figure(result, path: str | Path) -> dict:
    """Figure 4.6: the topple graph, poses coloured by V_s, arrows labelled with the best
    push's probability.  Returns {"nodes": P, "edges": E}."""
    plt = _pyplot()
    n = len(result.poses)
    v_s = np.array([s.quality for s in result.suction])
    angles = np.pi / 2 - 2 * np.pi * np.arange(n) / max(n, 1)
    xy = np.column_stack([np.cos(angles), np.sin(angles)]) * (0 if n == 1 else 1)
    edges = topple_edges(result)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    for (a, b), probability in edges.items():
        ax.annotate("", xy=xy[b], xytext=xy[a],
                    arrowprops={"arrowstyle": "-|>", "color": "0.4", "shrinkA": 16, "shrinkB": 16,
                                "connectionstyle": "arc3,rad=0.12"})
        middle = (xy[a] + xy[b]) / 2 + 0.06 * np.array([-(xy[b] - xy[a])[1], (xy[b] - xy[a])[0]])
        ax.text(*middle, edge_label(probability), fontsize=7, ha="center", va="center", color="0.2")
    nodes = ax.scatter(xy[:, 0], xy[:, 1], s=600, c=v_s, cmap="RdYlGn", vmin=0, vmax=1,
                       edgecolors=NODE_EDGE_COLOR, linewidths=2.5, zorder=3)
    for i in range(n):
        ax.text(*xy[i], str(i), ha="center", va="center", fontsize=9, zorder=4)
    fig.colorbar(nodes, ax=ax, shrink=0.7, label="V_s")
    ax.set_title(f"{result.object_id}: topple graph ({n} poses; arrows: best push's P(x'|x,u))", fontsize=9)
    ax.set_xlim(-1.4, 1.4), ax.set_ylim(-1.4, 1.4), ax.set_aspect("equal"), ax.axis("off")
    fig.savefig(path)
    plt.close(fig)
    return {"nodes": n, "edges": len(edges)}


def scene_file(obj, result, pose: int, path: str | Path) -> None:
    """The object in ``pose`` and its ``ok`` contacts (colour = P(topple)) as a GLB file."""
    import matplotlib
    import trimesh

    from schema.vocabulary import STATUS_NAMES

    mesh = obj.mesh.copy()
    mesh.apply_transform(result.poses[pose].transform)
    actions, table = result.actions[pose], result.topple[pose]
    ok = np.array([STATUS_NAMES[s] == "ok" for s in actions.status])
    colours = (matplotlib.colormaps["viridis"](np.nan_to_num(np.asarray(table.p_topple, dtype=float))[ok]) * 255).astype(np.uint8)
    scene = trimesh.Scene([mesh, trimesh.PointCloud(actions.points[ok], colors=colours)])
    Path(path).write_bytes(scene.export(file_type="glb"))


def main(argv: list[str] | None = None) -> int:
    from ..cli import path_arg
    from ..model.config import Config
    from ..model.evaluation import evaluate_object
    from ..model.mesh import UNIT_SCALES, MeshError, load_mesh

    parser = argparse.ArgumentParser(prog="toppledb figures", description=__doc__.split("\n\n")[0])
    parser.add_argument("mesh", type=Path, help="OBJ, STL or PLY file")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--units", choices=sorted(UNIT_SCALES), help="the file's length unit (as toppledb dataset's --units)")
    size.add_argument("--scale", type=float, help="metres per file unit (default: 1)")
    parser.add_argument("--mass", type=float, default=None, help="kg (default: mesh.default_mass)")
    parser.add_argument("--pose", type=int, default=0, help="pose of figure 4.5 (default: %(default)s)")
    parser.add_argument("--contacts", type=int, default=200, help="candidate pushes per pose (default: %(default)s)")
    parser.add_argument("--trials", type=int, default=20, help="trials per push (default: %(default)s)")
    parser.add_argument("--out", type=path_arg, default=Path("figures"), help="directory (default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        config = Config().with_overrides({"contacts.n_contacts": args.contacts, "topple.n_trials": args.trials})
        scale = UNIT_SCALES[args.units] if args.units else 1.0 if args.scale is None else args.scale
        obj = load_mesh(args.mesh, scale=scale, mass=args.mass, config=config.mesh)
        result = evaluate_object(obj, config)
    except (MeshError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if not 0 <= args.pose < len(result.poses):
        print(f"error: --pose {args.pose}: {result.object_id} has poses 0..{len(result.poses) - 1}", file=sys.stderr)
        return 2
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"error: cannot create {args.out}: {err.strerror}", file=sys.stderr)
        return 2
    drawn = pushes_figure(obj, result, args.pose, args.out / f"pushes_{args.pose}.png")
    graph = graph_figure(result, args.out / "graph.png")
    scene_file(obj, result, args.pose, args.out / "object.glb")
    print(f"{args.out}/pushes_{args.pose}.png: {drawn['contacts']} contacts; {args.out}/graph.png: "
          f"{graph['nodes']} poses, {graph['edges']} arrows; {args.out}/object.glb")
    return 0
