"""Two commits' code side by side in one run: a bench script of this directory run on each,
alternately, so that both see the same machine at the same time.

Each commit is checked out once into a temporary git worktree (removed at the end); the
bench script of that commit runs there with that commit's ``src`` first on the path, with
``--json``, ``--rounds`` times for each commit in the order A B A B ... (a first untimed
round for each warms the caches, numba's compiled kernels included).  The table gives, for
every row of the bench's JSON output and every chosen field, each commit's median over the
rounds and the ratio B / A.  A shared 2-core VM drifts by 10-15 % within the hour, which is
why the rounds alternate, and why a ratio within a few per cent of 1 is noise.

    python bench/ab.py --a 43bc16c --b HEAD --rounds 3 --fields step_ms_median,step_ms_p99 \\
        -- step.py --rvs 500 --predictors hgp
    python bench/ab.py --a 43bc16c --b HEAD --fields tick_ms_p50,tick_ms_p99,obu_cpu_pct \\
        -- obu_load.py --rvs 500 --per 50 --predictors hgp --seconds 10

When the old code lacks a flag, or the two are to run in different modes, ``--a-args`` and
``--b-args`` append to one side's command line only, and ``--key`` names the rows without
the field that differs (the issue's baseline, verifying everything, against today's
verify on demand, with the RVE signing the whole run before its clock starts):

    python bench/ab.py --a 43bc16c --rounds 1 --key rvs,per,predictor \
        --fields tick_ms_p99,deadline_misses --a-args "--verify on" \
        --b-args "--verify on-demand --sign-lookahead 16" \
        -- obu_load.py --rvs 500,1000 --per 0 --predictors hgp --seconds 15

The bench's JSON is a list of rows or an object with ``rows``; a row is named by its
``--key`` fields (default: those of rvs, per, predictor, verify, web_clients it has).
``--json`` prints the result as JSON instead of a table.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]


def _rows(doc) -> list[dict]:
    return doc["rows"] if isinstance(doc, dict) else doc


def _name(row: dict, keys: list[str]) -> tuple:
    return tuple((k, row[k]) for k in keys if k in row)


def _run(tree: Path, argv: list[str]) -> list[dict]:
    env = dict(os.environ, PYTHONPATH=str(tree / "src"), OPENBLAS_NUM_THREADS="1")
    cmd = [sys.executable, str(tree / "bench" / argv[0]), *argv[1:], "--json"]
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed in {tree}:\n{out.stderr[-2000:]}")
    return _rows(json.loads(out.stdout))


def compare(a: str, b: str, argv: list[str], fields: list[str], rounds: int,
            keys: list[str], extra: dict[str, list[str]] | None = None) -> list[dict]:
    """Each row's fields: the medians over ``rounds`` alternating runs of A and B
    (``extra``: arguments appended for one side, by ``a`` or ``b``)."""
    extra = extra or {}
    with tempfile.TemporaryDirectory(prefix="catc-ab-") as tmp:
        trees = {}
        for label, rev in (("a", a), ("b", b)):
            trees[label] = Path(tmp) / label
            subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q",
                            str(trees[label]), rev], check=True)
        try:
            values: dict[tuple, dict[str, dict[str, list[float]]]] = {}
            runs = [(r, label) for r in range(rounds + 1) for label in ("a", "b")]
            for r, label in tqdm(runs, desc="ab", unit="run", file=sys.stderr):
                rows = _run(trees[label], argv + extra.get(label, []))
                if r == 0:
                    continue  # warm-up round
                for row in rows:
                    slot = values.setdefault(_name(row, keys), {})
                    for f in fields:
                        if isinstance(row.get(f), int | float):
                            slot.setdefault(f, {"a": [], "b": []})[label].append(float(row[f]))
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force",
                                str(tree)], check=False)
    out = []
    for name, by_field in values.items():
        for f, v in by_field.items():
            # a field only one side's bench reports (an old one lacks it): its median
            ma = statistics.median(v["a"]) if v["a"] else None
            mb = statistics.median(v["b"]) if v["b"] else None
            out.append({"row": dict(name), "field": f, "a": v["a"], "b": v["b"],
                        "a_median": ma, "b_median": mb,
                        "ratio": round(mb / ma, 3) if ma and mb is not None else None})
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        print("ab: give the bench after --, e.g. -- step.py --rvs 500", file=sys.stderr)
        return 2
    cut = argv.index("--")
    ap = argparse.ArgumentParser(prog="ab", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", required=True, metavar="REV", help="the reference commit")
    ap.add_argument("--b", default="HEAD", metavar="REV", help="the commit compared (HEAD)")
    ap.add_argument("--rounds", type=int, default=3, help="timed runs of each (default 3)")
    ap.add_argument("--fields", required=True, help="comma-separated numeric fields")
    ap.add_argument("--key", default="rvs,per,predictor,verify,web_clients",
                    help="the fields that name a row (default %(default)s)")
    ap.add_argument("--a-args", default="", metavar="ARGS",
                    help="appended to A's command line only (one string, split as a shell does)")
    ap.add_argument("--b-args", default="", metavar="ARGS",
                    help="appended to B's command line only")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = ap.parse_args(argv[:cut])
    bench = argv[cut + 1:]
    if not bench or not (REPO / "bench" / bench[0]).is_file():
        print(f"ab: no bench script {bench[:1]} in bench/", file=sys.stderr)
        return 2
    try:
        result = compare(args.a, args.b, bench, args.fields.split(","), args.rounds,
                         args.key.split(","), {"a": shlex.split(args.a_args),
                                               "b": shlex.split(args.b_args)})
    except (RuntimeError, subprocess.CalledProcessError) as err:
        print(f"ab: {err}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({"a": args.a, "b": args.b, "bench": bench, "rounds": args.rounds,
                          "a_args": args.a_args, "b_args": args.b_args,
                          "results": result}, indent=1))
        return 0
    print(f"{' '.join(bench)}: A = {args.a} {args.a_args}, B = {args.b} {args.b_args}, "
          f"median of {args.rounds} alternating runs each")
    print(f"{'row':<44} {'field':<18} {'A':>10} {'B':>10} {'B/A':>6}")
    for r in result:
        name = ", ".join(f"{k} {v}" for k, v in r["row"].items())
        a, b = (f"{m:.3f}" if m is not None else "-" for m in (r["a_median"], r["b_median"]))
        print(f"{name[:44]:<44} {r['field']:<18} {a:>10} {b:>10} "
              f"{r['ratio'] if r['ratio'] is not None else '-':>6}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
