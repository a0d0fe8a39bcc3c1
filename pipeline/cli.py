"""Command line: ``toppledb COMMAND`` (or ``python -m pipeline COMMAND``).

    toppledb dataset [--corpus default|pybullet_data|DIR|LIST.csv] [--out data/dataset]
                     [--limit N] [--contacts N] [--trials N] [--variant NAME] [--seed S]
                     [--workers N | --scheduler ADDRESS] [--force] [--strict]
                     [--config FILE.toml|PRESET] [--set section.key=value ...]
    toppledb verify DIR
    toppledb corpus [--out pipeline/build/corpus_default.csv] [--count 189]
    toppledb policies DIR [--trials 20000] [--plot PNG]
    toppledb bench | report | calibrate | recalibrate | serve [their own options]
    toppledb --version

Parameters: defaults (``pipeline.model.config``), then ``--config``, then each ``--set``,
then the dedicated flags (``--contacts`` etc.).  Bad arguments, paths or
parameters give one line on stderr and exit status 2; a failed build exits 1.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path

from .model.config import PRESETS, VARIANTS, Config

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130

DELEGATED = {
    "bench": ("pipeline.studies.bench", "time the engine, suction and value iteration on one core (make bench)"),
    "report": ("pipeline.studies.validation", "score the model variants against push logs (validation report)"),
    "calibrate": ("pipeline.studies.calibrate", "search the noise parameters on push logs, write a config TOML"),
    "recalibrate": ("pipeline.studies.recalibrate", "refit the maps of P(topple) on push logs (monotone, down, side, boosted, or all in turn), write a config TOML"),
    "serve": ("service.__main__", "serve a finished dataset over HTTP (make serve)"),
    "figures": ("pipeline.studies.figures", "draw thesis figures 4.5 and 4.6 for a mesh (PNG) and a 3D view (GLB)"),
    "play": ("pipeline.studies.playlog", "play pushes in pybullet and write a push-outcome log"),
    "policies-physics": ("pipeline.studies.policies_physics", "play each policy's pushes in pybullet from dropped poses"),
    "landing": ("pipeline.studies.landing", "release every topple at its apex in pybullet; score where the model says it lands"),
    "heaps": ("pipeline.heaps.experiment", "pushing in clutter: hard heaps, five push policies, confidence gains (thesis ch. 3)"),
}
"""Commands with parsers of their own: ``toppledb NAME ARGS`` runs ``MODULE.main(ARGS)``."""
COMMANDS = ("dataset", "add", "verify", "corpus", "policies", *DELEGATED)


class UsageError(ValueError):
    """Bad command-line input; the message is one line."""


def print_and_record(text: str, record: dict, path: Path | None) -> int:
    """How a study ends: its text on stdout and, when ``path`` is given, its record there as JSON.
    returns : the exit code, 0, or 2 with one line on stderr when the record cannot be written"""
    from .build.atomic import write_json_atomic

    print(text)
    if path is not None:
        try:
            write_json_atomic(path, record)
        except OSError as err:
            print(f"error: cannot write {path}: {err.strerror or err}", file=sys.stderr)
            return 2
    return 0


def output_problem(*paths: Path | None, directory: bool = False) -> str | None:
    """Why one of a run's outputs could not be written, checked before a long run rather than found
    after it: a file (or, with ``directory``, a non-directory) in the output's place, a file where a
    parent directory should be, or no permission.  Missing parents are fine: the atomic writers
    create them.  A file is written beside its target and renamed over it, so its directory must
    let one create files even when the file itself exists; a directory's files are written inside it.
    None when every given path (None: not asked for) looks writable."""
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        try:
            exists = path.exists()
            if exists and path.is_dir() != directory:
                return f"cannot write {path}: it is {'not ' if directory else ''}a directory"
            ancestor = path.parent
            while not ancestor.exists() and ancestor != ancestor.parent:
                ancestor = ancestor.parent
            if not ancestor.is_dir():
                return f"cannot write {path}: {ancestor} is not a directory"
            targets = ([path] if exists else []) + ([] if exists and directory else [ancestor])
        except OSError as err:  # exists() raises, not answers, inside a directory one may not enter
            return f"cannot write {path}: {err.strerror or err}"
        if not all(os.access(target, os.W_OK | (os.X_OK if target.is_dir() else 0)) for target in targets):
            return f"cannot write {path}: permission denied"
    return None


def refused_outputs(*files: Path | None, directories: tuple[Path | None, ...] = (), figures: tuple[Path | None, ...] = ()) -> bool:
    """A run's outputs checked before it works (``output_problem``, ``plot_problem``): the first
    problem as one line on stderr.  returns : whether one was found (the run then exits 2)"""
    problem = (output_problem(*files) or output_problem(*directories, directory=True)
               or next(filter(None, map(plot_problem, figures)), None))
    if problem:
        print(f"error: {problem}", file=sys.stderr)
    return problem is not None


def plot_problem(path: Path | None) -> str | None:
    """``output_problem`` for a figure, and a format matplotlib writes, named by its suffix."""
    if path is None:
        return None
    from matplotlib.backend_bases import FigureCanvasBase

    from .build.atomic import figure_format

    suffix = figure_format(path)
    if suffix not in FigureCanvasBase.get_supported_filetypes():
        return f"cannot draw {path}: {f'no format is named {suffix!r}' if suffix else 'no suffix names its format'}; name it .png, .pdf or .svg"
    return output_problem(path)


def path_text(text: str) -> str:
    """An argparse type for a path: refuses the empty string, which ``Path`` would read as the working
    directory (``--out ""`` from an unset shell variable built a dataset into it)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; name a file or directory ('.' is the working directory)")
    return text


def path_arg(text: str) -> Path:
    """``path_text`` as a ``Path``."""
    return Path(path_text(text))


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
    return value


def corpus_units(args: argparse.Namespace):
    """The --units/--scale/--mass/--density flags as ``corpus.Units``."""
    from .build.corpus import Units
    from .model.mesh import UNIT_SCALES

    if args.units and args.scale:
        raise UsageError("give --units or --scale, not both")
    if args.mass and args.density:
        raise UsageError("give --mass or --density, not both")
    scale = UNIT_SCALES[args.units] if args.units else args.scale
    return Units(scale=scale, mass=args.mass, density=args.density)


def parser() -> argparse.ArgumentParser:
    from schema.version import SCHEMA_VERSION

    from . import __version__

    main = argparse.ArgumentParser(prog="toppledb", description="toppledb: build, check, study and serve datasets")
    # The schema beside the package: a dataset of another schema version is refused by this code.
    main.add_argument("--version", action="version", version=f"toppledb {__version__} (dataset schema {SCHEMA_VERSION})")
    commands = main.add_subparsers(dest="command", required=True, metavar="{" + ",".join(COMMANDS) + "}")

    defaults = Config()
    dataset = commands.add_parser(
        "dataset",
        help="build (or resume building) a dataset",
        description="Build, resume or extend a dataset.  A finished dataset in --out stays intact\n"
        "until the new one is complete; a run with nothing to do writes nothing.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=dataset_epilog(defaults),
    )
    dataset.add_argument(
        "--corpus",
        default="default",
        type=path_text,
        help="'default' (the committed 189-object list), 'pybullet_data' (every candidate), "
        "a directory of OBJ/STL/PLY meshes (units: see below), or a CSV list with columns "
        "path[,scale,mass,object_id,source,sha256] (default: %(default)s)",
    )
    dataset.add_argument("--out", default="data/dataset", type=path_text, help="dataset directory (default: %(default)s)")
    dataset.add_argument("--limit", type=positive_int, metavar="N", help="only the first N objects of the corpus")
    dataset.add_argument("--contacts", type=int, metavar="N", help=f"candidate pushes per pose (contacts.n_contacts, default: {defaults.contacts.n_contacts})")
    dataset.add_argument("--trials", type=int, metavar="N", help=f"Monte Carlo trials per push (topple.n_trials, default: {defaults.topple.n_trials})")
    dataset.add_argument("--variant", choices=VARIANTS, help=f"toppling model variant (topple.variant, default: {defaults.topple.variant})")
    dataset.add_argument("--seed", type=int, help=f"root of every random stream (seed, default: {defaults.seed})")
    _add_execution(dataset)
    units = dataset.add_argument_group(
        "units and mass (a directory corpus; they override the sidecar's defaults, not its per-mesh entries)"
    )
    units.add_argument("--units", choices=("mm", "cm", "m", "in"), help="the meshes' length unit (scale 0.001, 0.01, 1, 0.0254)")
    units.add_argument("--scale", type=positive_float, help="metres per file unit, e.g. 0.001 for millimetres")
    units.add_argument("--mass", type=positive_float, metavar="KG", help="mass of every mesh, kg")
    units.add_argument("--density", type=positive_float, metavar="KG/M3", help="mass = density x volume, e.g. 1000 for water")
    dataset.add_argument("--force", action="store_true", help="recompute every object, replacing what --out holds once the new dataset is complete")
    dataset.add_argument("--strict", action="store_true", help="stop at the first object that fails (exit 1; --out is left as it was)")

    add = commands.add_parser(
        "add",
        help="add one mesh to a finished dataset, computing only it",
        description="Add one mesh to a finished dataset with the dataset's own parameters; only the new object "
        "is computed and the manifest is replaced atomically (a running service picks it up on reload).",
    )
    add.add_argument("directory", type=path_text, help="a finished dataset")
    add.add_argument("mesh", type=path_arg, help="OBJ, STL or PLY file")
    add.add_argument("--id", dest="object_id", help="object id (default: from the file name)")
    add.add_argument("--units", choices=("mm", "cm", "m", "in"), help="the mesh's length unit")
    add.add_argument("--scale", type=positive_float, help="metres per file unit (default: 1)")
    add.add_argument("--mass", type=positive_float, metavar="KG", help="kg (default: the dataset's mesh.default_mass)")
    add.add_argument("--density", type=positive_float, metavar="KG/M3", help="mass = density x volume")
    add.add_argument("--no-progress", action="store_true", help="no progress bar")

    verify = commands.add_parser("verify", help="check a dataset against its manifest")
    verify.add_argument("directory", type=path_text, help="dataset directory")

    policies = commands.add_parser("policies", help="replay the thesis 4.4.3 policy experiment on a dataset")
    policies.add_argument("directory", type=path_text, help="dataset directory")
    policies.add_argument("--trials", type=positive_int, default=20_000, help="trials (default: %(default)s)")
    policies.add_argument("--steps", type=positive_int, default=5, help="most pushes per trial (default: %(default)s, the thesis's)")
    policies.add_argument("--seed", type=int, default=0, help="seed of the trial draws (default: %(default)s)")
    policies.add_argument("--plot", type=Path, metavar="PNG", help="also draw the mean gains to this file")

    corpus = commands.add_parser("corpus", help="regenerate the default corpus list (thesis 4.4.1 selection)")
    corpus.add_argument("--out", default=None, type=path_text, help="list to write (default: pipeline/build/corpus_default.csv)")
    corpus.add_argument("--count", type=positive_int, default=189, help="objects to keep (default: %(default)s)")
    corpus.add_argument("--limit", type=positive_int, metavar="N", help="consider only the first N candidates")
    _add_execution(corpus)

    for name, (_, text) in DELEGATED.items():
        commands.add_parser(name, help=f"{text} (see toppledb {name} --help)", add_help=False)
    return main


def dataset_epilog(defaults: Config) -> str:
    """Examples, the directory sidecar and every --set key with its default and range."""
    from .build.corpus import SIDECAR_HELP
    from .model.config import parameter_table

    examples = """\
examples:
  toppledb dataset                                        # default corpus -> data/dataset
  toppledb dataset --limit 5 --contacts 200 --out /tmp/small
  toppledb dataset --corpus meshes/ --units mm --density 700 --out data/mine
  toppledb dataset --corpus list.csv --set topple.mu_table_mean=0.5 --config params.toml
  toppledb dataset --config thesis --out data/thesis     # a preset: the thesis's model
  toppledb dataset --scheduler tcp://head:8786            # on a dask.distributed cluster
  toppledb add data/dataset part.stl --units mm --mass 0.2

exit status: 0 done, 1 build failed (or every object failed), 2 bad arguments or paths,
130 interrupted (SIGINT/SIGTERM; the same command resumes)."""
    keys = ["--set keys (SECTION.KEY=VALUE; default, accepted range):"]
    for key, value, accepted in parameter_table(defaults):
        shown = f"{value:.6g}" if isinstance(value, float) else str(value)
        if isinstance(value, tuple):  # knots: a list, comma-separated with --set
            shown, accepted = f"{len(value)} values", f"each {accepted}" if accepted else accepted
        keys.append(f"  {key:34s} {shown:>10s}  {accepted}")
    return "\n\n".join([examples, SIDECAR_HELP, "\n".join(keys)])


def _add_execution(command: argparse.ArgumentParser) -> None:
    from .build.fanout import default_workers

    command.add_argument("--workers", type=positive_int, help="local worker processes (default: all cores, here %s)" % default_workers())
    command.add_argument("--scheduler", metavar="ADDRESS", help="run on this dask.distributed scheduler, e.g. tcp://host:8786")
    presets = ", ".join(sorted(p.stem for p in PRESETS.glob("*.toml")))
    command.add_argument(
        "--config",
        type=Path,
        metavar="FILE.toml|PRESET",
        help=f"parameters from a TOML file, or a preset by name: {presets} (e.g. --config thesis, the thesis's model)",
    )
    command.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one parameter, e.g. --set topple.mu_table_mean=0.5 (repeatable)",
    )
    command.add_argument("--no-progress", action="store_true", help="no progress bar")


def make_config(args: argparse.Namespace) -> Config:
    """Defaults, then --config, then --set, then the dedicated flags."""
    if args.config is not None:
        path = Path(args.config)
        if not path.is_file() and (PRESETS / f"{args.config}.toml").is_file():
            path = PRESETS / f"{args.config}.toml"  # a preset name, e.g. --config thesis
        if not path.is_file():
            presets = ", ".join(sorted(p.stem for p in PRESETS.glob("*.toml")))
            raise UsageError(f"config file not found: {args.config} (presets: {presets})")
        try:
            config = Config.from_toml(path)
        except tomllib.TOMLDecodeError as err:
            raise UsageError(f"{args.config}: not valid TOML ({err})") from None
        except ValueError as err:
            raise UsageError(f"{args.config}: {err}") from None
    else:
        config = Config()
    overrides = {}
    for item in args.overrides:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set expects SECTION.KEY=VALUE, got {item!r}")
        overrides[key.strip()] = value.strip()
    flags = {
        "contacts.n_contacts": getattr(args, "contacts", None),
        "topple.n_trials": getattr(args, "trials", None),
        "topple.variant": getattr(args, "variant", None),
        "seed": getattr(args, "seed", None),
    }
    overrides.update({k: v for k, v in flags.items() if v is not None})
    try:
        config = config.with_overrides(overrides) if overrides else config
    except ValueError as err:  # unknown key, wrong type, bad variant: the user's input
        raise UsageError(str(err)) from None
    if config.topple.applied_boosted_map:
        # Read the map the model names now, so a missing or broken file is the user's one-line error,
        # not a traceback from the first worker that evaluates a pose.
        from .model.boosted_map import BoostedMapError, load_trees

        try:
            load_trees(config.topple.applied_boosted_map)
        except BoostedMapError as err:
            raise UsageError(str(err)) from None
    return config


def run_dataset(args: argparse.Namespace) -> int:
    from .build.corpus import load_corpus
    from .build.dataset import build_dataset

    config = make_config(args)
    corpus = load_corpus(args.corpus, config.mesh.default_mass, corpus_units(args)).limit(args.limit)
    renamed = corpus.renamed()
    if renamed:  # otherwise only the manifest would say which id a file became
        shown = ", ".join(f"{name} -> {object_id}" for name, object_id in renamed[:5])
        more = f", and {len(renamed) - 5} more" if len(renamed) > 5 else ""
        print(f"ids: {len(renamed)} mesh{'es' if len(renamed) != 1 else ''} named otherwise than the file: {shown}{more} "
              "(the manifest's corpus lists every id)", file=sys.stderr)
    summary = build_dataset(
        corpus,
        config,
        args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        force=args.force,
        strict=args.strict,
        progress=not args.no_progress,
        log=lambda line: print(line, file=sys.stderr),
    )
    print(summary.text())
    if summary.committed:
        print(f"dataset: {Path(args.out).resolve()}")
    if summary.all_failed:
        print(f"error: every object failed ({summary.manifest.counts.failed}); see the reasons above. Nothing was "
              f"written: {args.out} is as it was", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def run_verify(args: argparse.Namespace) -> int:
    from schema.layout import MANIFEST
    from schema.manifest import read_manifest

    from .build.verify import verify_dataset

    directory = Path(args.directory)
    if not directory.is_dir() or not (directory / MANIFEST).is_file():
        # Not a dataset at all is a bad path (2), as for every other command; 1 is a dataset that fails its checks.
        what = "no such directory" if not directory.is_dir() else f"no {MANIFEST}: not a toppledb dataset"
        print(f"error: {directory}: {what}", file=sys.stderr)
        return EXIT_USAGE
    problems = verify_dataset(args.directory)
    for problem in problems:
        print(problem)
    if problems:
        print(f"verify: {len(problems)} problem(s) in {args.directory}", file=sys.stderr)
        return EXIT_FAILED
    counts = read_manifest(args.directory).counts
    print(
        f"ok: {args.directory}: {counts.objects} objects, {counts.poses} poses, "
        f"{counts.actions} actions, {counts.transitions} transitions verified"
    )
    return EXIT_OK


def run_corpus(args: argparse.Namespace) -> int:
    from .build.corpus import DEFAULT_LIST
    from .build.selection import regenerate_default

    config = make_config(args)
    out = Path(args.out) if args.out else DEFAULT_LIST
    counts = regenerate_default(
        config, out, count=args.count, limit=args.limit, workers=args.workers,
        scheduler=args.scheduler, progress=not args.no_progress,
    )
    for object_id, reason in counts["failures"].items():
        print(f"not evaluated: {object_id}: {reason}", file=sys.stderr)
    print(
        f"{counts['candidates']} candidates, {counts['failed']} failed to load or evaluate, "
        f"{counts['selected']} satisfy the selection rule, kept {counts['kept']} -> {out}"
    )
    if counts["kept"] < args.count:
        print(f"warning: only {counts['kept']} objects selected, fewer than {args.count}", file=sys.stderr)
    return EXIT_OK


def run_add(args: argparse.Namespace) -> int:
    from schema.layout import check_object_id
    from schema.manifest import ManifestError, read_manifest

    from .build.atomic import file_sha256
    from .build.corpus import ObjectSpec, mass_from_density, object_id_from_name
    from .build.dataset import add_object

    units = corpus_units(args)
    mesh = args.mesh.resolve()
    if not mesh.is_file():
        raise UsageError(f"mesh file not found: {args.mesh}")
    try:
        object_id = check_object_id(args.object_id or object_id_from_name(mesh.stem))
    except ValueError as err:
        raise UsageError(str(err)) from None
    scale = units.scale or 1.0
    mass = units.mass
    if units.density is not None:
        # None when the mesh does not load: ``add_object`` reads it before computing and says why (exit 2).
        mass = mass_from_density(mesh, scale, units.density)
    if mass is None:
        try:
            mass = float(read_manifest(args.directory).parameters.model_dump()["mesh"]["default_mass"])
        except (ManifestError, KeyError) as err:
            raise UsageError(f"cannot add to {args.directory}: {err}") from None
    spec = ObjectSpec(object_id, str(mesh), float(scale), float(mass), f"added:{mesh.name}", file_sha256(mesh))
    summary = add_object(args.directory, spec, log=lambda line: print(line, file=sys.stderr), progress=not args.no_progress)
    shard = summary.manifest.shards[object_id]
    print(f"added     {object_id}: {shard.counts.poses} poses, {shard.counts.actions} actions ({summary.wall_s:.1f} s)")
    print(summary.text())
    return EXIT_OK


def run_policies(args: argparse.Namespace) -> int:
    import json

    from schema.reader import Dataset, DatasetUnreadable

    from .studies.policy_experiment import experiment, plot, summary

    problem = plot_problem(args.plot)
    if problem:
        raise UsageError(problem)
    try:
        Dataset.open(args.directory)
    except DatasetUnreadable as err:
        raise UsageError(str(err)) from None
    result = experiment(args.directory, n_trials=args.trials, max_steps=args.steps, seed=args.seed)
    print(summary(result))
    if args.plot:
        plot(result, args.plot)
        print(f"plot: {args.plot}")
    for policy in result["policies"].values():
        policy.pop("gains_useful")
    print(json.dumps(result, allow_nan=False))  # a NaN would be no JSON at all; no useful trial is null
    return EXIT_OK


def run_command(command: Callable[[], int | None]) -> int:
    """A command's exit code, with the two ways a finished command can still fail said plainly:
    what the file system refuses after the command's own checks (a full disk, /proc) is one line
    and exit 2, not a traceback; a reader that stopped reading (``| head``) ends it quietly."""
    try:
        return command() or EXIT_OK
    except BrokenPipeError:
        # Nothing more can be written; point stdout at /dev/null so Python's exit does not
        # complain again while flushing it (the recipe of Python's signal documentation).
        with contextlib.suppress(AttributeError, ValueError, OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_FAILED
    except OSError as err:
        print(f"error: {err.filename}: {err.strerror or err}" if err.filename else f"error: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_USAGE


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in DELEGATED:
        # Before anything from pipeline.build: `toppledb serve` must work with only the service extra.
        from importlib import import_module

        module = import_module(DELEGATED[argv[0]][0])
        if argv[0] == "serve":  # its usage names the command typed: `toppledb serve`, or `python -m service`
            return module.main(argv[1:], prog="toppledb serve") or EXIT_OK
        return run_command(lambda: module.main(argv[1:]))
    from .build.corpus import CorpusError
    from .build.dataset import BuildError, InputError, OutputError
    from .build.fanout import SchedulerError

    args = parser().parse_args(argv)
    commands = {
        "dataset": run_dataset, "add": run_add, "verify": run_verify, "corpus": run_corpus, "policies": run_policies,
    }
    try:
        with _terminate_as_interrupt():
            return run_command(lambda: commands[args.command](args))
    except (UsageError, CorpusError, OutputError, InputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except (BuildError, SchedulerError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(
            "interrupted; workers stopped, a finished dataset is unchanged; run the same command again to resume",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM (a job scheduler, ``kill``) unwinds like Ctrl-C, so the build's cleanup
    runs and the loky workers are stopped instead of being orphaned."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
