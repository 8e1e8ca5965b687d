"""The ``plantdyn`` command line.

Exit codes (design.md): 0 success, 2 bad configuration or input (message on stderr),
1 internal error.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import traceback
from pathlib import Path

from flows.common import StageLines
from pipeline.errors import UserInputError


def _check_job(path: str, *, files: bool = True):
    """Everything that can be checked before work starts (config, paths, roots, storage,
    run id), once — so a bad job fails in a second, with one message, before Prefect."""
    from pipeline.adapters.config import load_job, resolve_sources

    cfg = load_job(path)
    if files:
        resolve_sources(cfg)
    root = cfg.storage_root
    if root.exists() and not root.is_dir():
        from pipeline.errors import ConfigError

        raise ConfigError(f"storage: {str(root)!r} is a file, not a folder")
    if root.is_dir():
        from pipeline.adapters.store import check_catalog

        check_catalog(root)  # a catalog that is not ours: exit 2 now, not after the work
    from pipeline.jobs.monitoring import check_baseline

    check_baseline(cfg)  # a pinned baseline run must exist (exit 2 naming the runs)
    return cfg


def _check_run_id(run_id: str | None) -> None:
    if run_id is not None:
        from pipeline.adapters.store import NAME_RE, check_name

        check_name(run_id, what="--run-id", pattern=NAME_RE)


def _run_workflow(args, direct, flow_name: str, run_flow, check=None) -> int:
    """Run a job's workflow — ``direct(cfg, run_id=, progress=)`` with ``--no-prefect``,
    else the flow ``run_flow()`` returns, as ``(job, run_id=)``, through Prefect — after
    the checks that need no data (``check(cfg)``), and print its report and run directory
    (stdout's last line)."""
    cfg = _check_job(args.job)
    _check_run_id(args.run_id)
    if check is not None:
        check(cfg)
    if args.no_prefect:
        report = direct(cfg, run_id=args.run_id, progress=StageLines())
    else:
        from flows.common import starting
        from flows.server import project_prefect

        with project_prefect(cfg.storage_root) as api, \
                starting(f"the Prefect flow '{flow_name}' (server {api})"):
            report = run_flow()(args.job, run_id=args.run_id, cfg=cfg)
    print(report, file=sys.stderr)
    print(report.run_dir)
    return 0


def _cmd_run(args) -> int:
    from pipeline.jobs.estimation import run_job

    def flow():
        from flows.estimate import run_estimate

        return run_estimate

    return _run_workflow(args, run_job, "estimate", flow)


def _cmd_nightly(args) -> int:
    cfg = _check_job(args.job, files=False)  # an empty drop folder is a normal night
    if args.no_prefect:
        from pipeline.jobs.nightly import run_nightly_direct

        rows = run_nightly_direct(cfg, retry_failed=args.retry_failed,
                                  say=lambda line: print(line, file=sys.stderr, flush=True))
    else:
        from flows.common import starting
        from flows.server import project_prefect

        with project_prefect(cfg.storage_root) as api, \
                starting(f"the Prefect flow 'nightly' (server {api})"):
            from flows.nightly import run_nightly

            rows = run_nightly(args.job, retry_failed=args.retry_failed, cfg=cfg)
    for r in rows:  # one line per file: status, run dir or message
        where = r.get("run_dir") or r.get("run_id") or ""
        print(f"{r['status']:>10}  {Path(r['path']).name}  {where}  {r.get('error') or ''}"
              .rstrip())
    return _nightly_summary(args.job, rows)


def _nightly_summary(job: str, rows: list[dict]) -> int:
    """The nightly's summary on stderr and its exit code (1 internal error, 2 bad data)."""
    counts = {s: sum(r["status"] == s for r in rows) for s in
              sorted({r["status"] for r in rows})}
    summary = ", ".join(f"{n} {s}" for s, n in counts.items()) or "no new files"
    print(f"nightly: {len(rows)} file(s): {summary}", file=sys.stderr)
    before = [r for r in rows if r["status"] == "skipped_failed_before"]
    if before:
        print(f"nightly: {len(before)} file(s) failed before with this job configuration and "
              f"were not tried again (first: {Path(before[0]['path']).name}); after fixing "
              f"them: plantdyn nightly {job} --retry-failed", file=sys.stderr)
    if any(r["status"] == "error" for r in rows):
        bad = next(r for r in rows if r["status"] == "error")
        print(f"plantdyn: internal error on {bad['path']} (exit 1; it is retried next night): "
              f"{bad.get('error')}", file=sys.stderr)
        return 1
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        print(f"plantdyn: error: {len(failed)} of {len(rows)} file(s) failed with bad data "
              f"(not retried until they or the job change, or --retry-failed): "
              f"{Path(failed[0]['path']).name}: {failed[0].get('error')}", file=sys.stderr)
        return 2
    return 0


def _cmd_runs(args) -> int:
    from flows.runs_view import show_runs
    from pipeline.adapters.config import load_job
    from pipeline.adapters.store import ResultStore

    if args.job.endswith((".yaml", ".yml")):
        cfg = load_job(args.job)
        root, job = cfg.storage_root, cfg.job
    else:
        from pipeline.adapters.safe_write import check_path_length

        root, job = check_path_length(args.storage, "--storage").resolve(), args.job
    # read-only: listing never creates a catalog (a --storage typo) nor needs write access
    # (an archive on a read-only disk)
    store = ResultStore(root, readonly=True)
    return show_runs(store, job, metrics=args.metric, plot=args.plot, draw=not args.no_plot,
                     force=args.force)


def _cmd_reindex(args) -> int:
    from pipeline.adapters.safe_write import check_path_length
    from pipeline.adapters.store import ResultStore

    root = check_path_length(args.storage, "STORAGE").resolve()
    res = ResultStore.reindex_folder(root, force=args.force)
    for note in res.notes:
        print(note)
    print(f"catalog rebuilt from {res.n_runs} run folder(s) under {root}")
    for s in res.skipped:
        print(f"  skipped {s}")
    return 0


def _cmd_demo(args) -> int:
    if args.discrepancy or args.two_effects:  # --two-effects implies --discrepancy
        from flows.demo import run_discrepancy_demo

        return run_discrepancy_demo(Path(args.dir), no_prefect=args.no_prefect,
                                    progress=StageLines(), two_effects=args.two_effects)
    from flows.demo import run_demo

    return run_demo(Path(args.dir), no_prefect=args.no_prefect, progress=StageLines())


def _cmd_serve(args) -> int:
    from flows.serve import serve

    jobs = args.jobs if args.jobs else sorted(str(q) for q in Path("configs").glob("*.yaml"))
    if not jobs:
        from pipeline.errors import ConfigError

        raise ConfigError(f"no job YAMLs given and none in {Path('configs').resolve()}; give "
                          "the jobs to serve: plantdyn serve JOB.yaml ...")
    return serve([Path(p) for p in jobs], limit=args.limit, once=args.once)


def _cmd_server(args) -> int:
    from flows.server import (
        configured_api_url,
        ensure_server,
        server_home,
        server_status,
        stop_server,
    )

    if args.job:
        from pipeline.adapters.config import load_job

        root = load_job(args.job).storage_root
    else:
        from pipeline.adapters.safe_write import check_path_length

        root = check_path_length(args.storage, "--storage").resolve()
    home = server_home(root)
    if args.action == "start":
        st = ensure_server(home)
        print(f"running: {st.api_url} (pid {st.pid}); dashboard "
              f"{st.api_url.removesuffix('/api')}; stop it with plantdyn server stop")
    elif args.action == "stop":
        print(stop_server(home))
    else:
        print(server_status(home).describe())
    configured = configured_api_url()
    if configured and args.action != "stop":
        print(f"note: PREFECT_API_URL={configured} is set: commands use that server, not "
              "this one", file=sys.stderr)
    return 0


def _cmd_discrepancy(args) -> int:
    from pipeline.jobs.discrepancy import check_job, run_discrepancy

    def flow():
        from flows.discrepancy import run_discrepancy_flow

        return run_discrepancy_flow

    # check_job: model and settings errors before reading data
    return _run_workflow(args, run_discrepancy, "discrepancy", flow, check=check_job)


def _cmd_export(args) -> int:
    from pipeline.adapters.export import export_run

    res = export_run(args.run_dir, fmt=args.format, out=args.out, force=args.force,
                     progress=StageLines())
    for note in res.notes:
        print(note, file=sys.stderr)
    print(res.path)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="plantdyn",
        description="Step responses of every input->output pair from normal operating data.")
    sub = p.add_subparsers(dest="command", required=True)
    shown = argparse.ArgumentParser(add_help=False)
    shown.add_argument("--progress", choices=("auto", "always", "never"), default="auto",
                       help="progress bars with rate and ETA on long work: auto (when stderr "
                            "is a terminal), always (plain lines off a terminal), never")
    r = sub.add_parser("run", help="run an estimation job; prints the run directory",
                       parents=[shown])
    r.add_argument("job", help="job YAML file")
    r.add_argument("--run-id", default=None, help="run id (default: UTC time + random)")
    r.add_argument("--no-prefect", action="store_true",
                   help="call the pipeline directly instead of through the Prefect flow")
    r.set_defaults(fn=_cmd_run)
    n = sub.add_parser("nightly", help="process new files of a job's drop folder once each",
                       parents=[shown])
    n.add_argument("job")
    n.add_argument("--no-prefect", action="store_true",
                   help="process the files directly (threads, or the dask.address cluster) "
                        "instead of through the Prefect flow")
    n.add_argument("--retry-failed", action="store_true",
                   help="try again the files that failed with bad data before (otherwise "
                        "skipped until the file or the job's configuration changes)")
    n.set_defaults(fn=_cmd_nightly)
    d = sub.add_parser("demo", help="make a demo historian export and run the demo job",
                       parents=[shown])
    d.add_argument("--dir", default="demo",
                   help="folder for the demo export and job (default: ./demo in the current "
                        "folder; results go to ./storage beside it)")
    d.add_argument("--no-prefect", action="store_true")
    d.add_argument("--discrepancy", action="store_true",
                   help="the discrepancy demo instead: a plant whose controller gain is 20 %% "
                        "above the model's (configs/demo_discrepancy.yaml)")
    d.add_argument("--two-effects", action="store_true",
                   help="the discrepancy demo with a plant that also has an auxiliary flow the "
                        "model ignores; two effects are named in order "
                        "(configs/demo_discrepancy_two.yaml)")
    d.set_defaults(fn=_cmd_demo)
    s = sub.add_parser("serve", help="serve the scheduled (nightly) deployments")
    s.add_argument("jobs", nargs="*", default=None,
                   help="job YAMLs with a 'schedule:' (default: ./configs/*.yaml)")
    s.add_argument("--limit", type=int, default=1, help="concurrent runs")
    s.add_argument("--once", action="store_true",
                   help="register the deployments, run each once now, and exit")
    s.set_defaults(fn=_cmd_serve)
    sv = sub.add_parser("server", help="the project's local Prefect server that run, "
                                       "discrepancy, nightly, demo and serve start and reuse")
    sv.add_argument("action", choices=("start", "stop", "status"),
                    help="start (or find) it, stop it, or say whether it runs")
    where = sv.add_mutually_exclusive_group()
    where.add_argument("--storage", default="storage",
                       help="results root whose server (state in <storage>/.prefect, or "
                            "$PREFECT_HOME when set) is meant (default: ./storage)")
    where.add_argument("--job", default=None,
                       help="a job YAML: the server of its storage root")
    sv.set_defaults(fn=_cmd_server)
    ru = sub.add_parser("runs", help="list runs of a job (pairs changed against the "
                                     "monitoring baseline first) and plot its trend")
    ru.add_argument("job", help="job name or job YAML")
    ru.add_argument("--storage", default="storage",
                    help="results root when JOB is a name (default: ./storage)")
    ru.add_argument("--metric", action="append", help="metrics to trend (repeatable)")
    ru.add_argument("--plot", default=None, metavar="FILE",
                    help="where to write the trend figure (PNG; default "
                         "<storage>/<job>/trend.png)")
    ru.add_argument("--no-plot", action="store_true", help="do not write the trend figure")
    ru.add_argument("--force", action="store_true",
                    help="replace an existing --plot file (a regular file only)")
    ru.set_defaults(fn=_cmd_runs)
    rx = sub.add_parser("reindex", help="rebuild a results root's catalog from its run "
                                        "folders (after a read-only, lost, empty or foreign "
                                        "catalog: moved aside, never deleted)")
    rx.add_argument("storage", help="the results root (a job's storage: folder)")
    rx.add_argument("--force", action="store_true",
                    help="rebuild even if STORAGE does not look like a results store (no "
                         "catalog, no <job>/<run-id>/manifest.json run folders)")
    rx.set_defaults(fn=_cmd_reindex)
    dc = sub.add_parser("discrepancy", help="simulation-vs-measurement workflow; prints the "
                                            "run directory", parents=[shown])
    dc.add_argument("job", help="job YAML file with model: (or discrepancy.simulator_outputs)")
    dc.add_argument("--run-id", default=None, help="run id (default: UTC time + random)")
    dc.add_argument("--no-prefect", action="store_true",
                    help="call the pipeline directly instead of through the Prefect flow")
    dc.set_defaults(fn=_cmd_discrepancy)
    ex = sub.add_parser("export", help="write a run's step responses and fitted transfer "
                                       "functions for control tools; prints the file")
    ex.add_argument("run_dir", help="an estimation run directory (<storage>/<job>/<run-id>)")
    ex.add_argument("--format", required=True, choices=("csv", "json", "mat", "control"),
                    help="csv: DMC-style step-coefficient table; json: everything; mat: "
                         "MATLAB arrays; control: transfer functions for "
                         "pipeline.adapters.export.load_control (python-control)")
    ex.add_argument("--out", default=None,
                    help="file, or an existing folder (default: ./<job>_<run-id>.<ext> in the "
                         "current folder; never inside the run directory)")
    ex.add_argument("--force", action="store_true", help="replace an existing --out file")
    ex.set_defaults(fn=_cmd_export)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the ``plantdyn`` command; returns the exit code (0, 2 bad input, 1 internal error).

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments without the program name; ``None`` reads ``sys.argv``.
    """
    args = build_parser().parse_args(argv)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    if getattr(args, "progress", "auto") != "auto":
        from pipeline.adapters.progress import ENV

        os.environ[ENV] = "1" if args.progress == "always" else "0"
    try:
        return args.fn(args)
    except UserInputError as exc:
        print(f"plantdyn: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `plantdyn runs JOB | head`: the reader left, nothing to say
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("plantdyn: interrupted", file=sys.stderr)
        return 1
    except Exception:  # noqa: BLE001 - internal error: show it, exit 1
        traceback.print_exc()
        print("plantdyn: internal error (exit 1); please report it with the traceback above",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
