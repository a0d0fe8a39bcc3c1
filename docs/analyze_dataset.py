"""Reading a toppledb dataset with pandas, polars, duckdb and pyarrow, and one plot.

    .venv/bin/python docs/analyze_dataset.py [DATASET_DIR] [--plot FILE.png]

The plot goes to dataset_overview.png in the working directory unless --plot names another file; the
README's figure is this script on the default dataset with --plot docs/dataset_overview.png.

Every query here is also in docs/DATASET.md ("Reading the tables").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import duckdb
import matplotlib
import numpy as np

matplotlib.use("Agg")  # files only, no display needed
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
import polars as pl  # noqa: E402
import pyarrow.dataset as ds  # noqa: E402


def dataset_problem(root: Path) -> str | None:
    """Why ``root`` is not a finished dataset this script can read (no directory, no manifest.json), or None."""
    if not root.is_dir():
        return "no such directory; give a dataset directory (toppledb dataset --out DIR)"
    if not (root / "manifest.json").is_file():
        return "no manifest.json: not a finished toppledb dataset"
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", default="data/dataset", type=Path)
    # Not docs/ by default: a run on a small dataset would overwrite the README's figure.
    parser.add_argument("--plot", type=Path, default=Path("dataset_overview.png"))
    args = parser.parse_args()
    root = args.dataset
    problem = dataset_problem(root)
    if problem:
        # A bad path is the user's to fix: one line and exit 2, as the toppledb commands give, not a traceback.
        print(f"error: {root}: {problem}", file=sys.stderr)
        sys.exit(2)

    # pandas: the consolidated tables are single files; partitioned ones read as one table.
    poses = pd.read_parquet(root / "poses.parquet")
    actions = pd.read_parquet(root / "actions", columns=["object_id", "pose", "action", "status", "p_topple"])
    print(f"pandas: {len(poses)} poses, {len(actions)} actions")

    # polars: lazy scan of the hive-partitioned actions, only the rows and columns needed.
    topple_by_object = (
        pl.scan_parquet(root / "actions" / "**" / "*.parquet", hive_partitioning=True)
        .filter(pl.col("status") == "ok")
        .group_by("object_id")
        .agg(pl.col("p_topple").mean().alias("mean_p_topple"), pl.len().alias("ok_actions"))
        .sort("mean_p_topple", descending=True)
        .collect()
    )
    print("polars: topple probability by object (top 5)")
    print(topple_by_object.head(5))

    # duckdb: join transitions with the poses they lead to: E[V_s(x')] of every action.
    con = duckdb.connect()
    expected_vs = con.execute(
        f"""
        select t.object_id, t.pose, t.action, s.v_s as v_s_now, sum(t.probability * p.v_s) as expected_v_s
        from read_parquet('{root}/transitions/*/*.parquet', hive_partitioning = true) t
        join '{root}/poses.parquet' p on p.object_id = t.object_id and p.pose = t.next_pose
        join '{root}/poses.parquet' s on s.object_id = t.object_id and s.pose = t.pose
        group by t.object_id, t.pose, t.action, s.v_s
        order by round(expected_v_s - v_s_now, 12) desc, t.object_id, t.pose, t.action
        limit 5
        """
    ).df()
    print("duckdb: the five pushes that raise the expected suction quality most over grasping now")
    print(expected_vs)

    # pyarrow: filters are pushed down to the partition directories.
    duck = ds.dataset(root / "actions", format="parquet", partitioning="hive")
    print("pyarrow: duck actions:", duck.count_rows(filter=ds.field("object_id") == "duck"))

    figure, (left, middle, right) = plt.subplots(1, 3, figsize=(15, 4))
    ranked = topple_by_object["mean_p_topple"].to_numpy()
    left.plot(range(len(ranked)), ranked)
    left.set(xlabel="object (ranked)", ylabel="mean P(topple) of ok pushes", title="Topple probability by object")
    # V_s is a share of suction.n_samples grasps (20), so it takes 21 values: one bar each, centred on it.
    # Bins of 0.1 would cut through them, and float edges (0.30000000000000004) move 0.3 one bin down.
    samples = json.loads((root / "manifest.json").read_text())["parameters"]["suction"]["n_samples"]
    values = np.arange(samples + 1) / samples
    counts = np.bincount(np.rint(poses["v_s"].to_numpy() * samples).astype(int), minlength=samples + 1)
    middle.bar(values, counts, width=0.8 / samples)
    middle.set(xlabel="V_s", ylabel="stable poses", title=f"Suction quality V_s over {len(poses)} poses")
    print(f"V_s by value (0, 1/{samples}, ..., 1):", counts.tolist(), f"mean {poses['v_s'].mean():.3f}")
    right.scatter(poses["v_s"], poses["v_t"], s=6, alpha=0.5)
    right.plot([0, 1], [0, 1], color="grey", linewidth=0.8)
    right.set(xlabel="V_s (grasp now)", ylabel="V_T (topple first, value iteration)", title="Value of each stable pose")
    figure.tight_layout()
    figure.savefig(args.plot, dpi=110)
    print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
