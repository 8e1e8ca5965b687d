"""Add the "explainable" bar to zoo suite rows already run: for each visible trial of
the chosen effects, the held-out gap reduction of the nominal model with the true effect
(:func:`tests.zoo.explainable.model_gap_reduction`), regenerated from the trial's family
and seed (the zoo is deterministic per seed).

Run:  .venv/bin/python -m tests.benchmarks.zoo_explain IN.jsonl... --out OUT.jsonl
          [--effects saturation deadband ...]

Writes every input row with ``model_gap_reduction`` added (NaN for rows not recomputed);
tabulate OUT with ``python -m tests.benchmarks.zoo_suite OUT.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import math

from tests.benchmarks.zoo_suite import INVISIBLE, NONE
from tests.zoo import FAMILIES
from tests.zoo.explainable import model_gap_reduction
from tests.zoo.trial import make_trial


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--effects", nargs="*", default=None)
    args = ap.parse_args(argv)
    with open(args.out, "w", encoding="utf-8") as out:
        for path in args.rows:
            for line in open(path, encoding="utf-8"):
                row = json.loads(line)
                value = math.nan
                if row["effect"] != NONE and row["label"] != INVISIBLE and (
                        args.effects is None or row["effect"] in args.effects):
                    trial = make_trial(FAMILIES[row["family"]], row["effect"], int(row["seed"]))
                    value = model_gap_reduction(trial)
                    print(f"{row['family']:>14} {row['effect']:>18} {row['seed']} "
                          f"{row['label']:>18} ideal {row['ideal_gap_reduction']:.3f} "
                          f"model {value:.3f}", flush=True)
                row["model_gap_reduction"] = value
                out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
