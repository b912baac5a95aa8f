"""Record the held-out standings of the learned policies from ``selenv bench`` JSON files.

A policy record's standing (:class:`selenv.families.policy.Standing`) is what ``selenv list``,
``learned`` and the docs show; it lives in the checkpoint JSON the record names, under
``"standings"``. This script fills it from bench runs, so no number is typed by hand::

    selenv bench selenv/FIMSelection-v1 --agents greedy,swap,ppo --seed 30000 --episodes 30 \
        --baseline greedy --json runs/standing/fim.json
    .venv/bin/python scripts/record_standings.py runs/standing/fim.json

For every env in each JSON and every agent of it that is a policy record (or a deprecated name
of one without options), the entry ``(agent, env_id, env_kwargs)`` is replaced by the run's:
the paired mean difference against the run's baseline with its 95 % CI and W/T/L, the decision
time over the baseline's, the seeds and the command. The run's baseline must be the record's
(``greedy``, or ``brute_force`` for the landmark policies); other agents are skipped with a
note. Each checkpoint JSON is rewritten atomically, keeping all its other keys.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from selenv.agents import parse_spec
from selenv.agents.learned import all_policies
from selenv.atomic import write_json
from selenv.families.policy import PolicySpec, read_standings
from selenv.learned.resources import read_metadata
from selenv.shipped import checkpoint_dir


def _record_for(name: str, env_id: str) -> PolicySpec | None:
    """The record agent ``name`` plays on ``env_id`` with the record's own options, if any."""
    for record in all_policies():
        if env_id not in record.plays:
            continue
        if record.name == name or (name in record.aliases and not record.aliases[name]):
            return record
    return None


def standings_of(doc: dict[str, Any]) -> list[tuple[PolicySpec, dict[str, Any]]]:
    """The ``(record, standing entry)`` pairs a bench JSON holds (notes on stderr for skips)."""
    argv = doc.get("provenance", {}).get("argv") or []
    command = shlex.join(argv)
    date = str(doc.get("provenance", {}).get("timestamp", ""))[:10]
    out: list[tuple[PolicySpec, dict[str, Any]]] = []
    for result in doc.get("results", []):
        env_id, baseline = result["env_id"], result["baseline"]
        agents = result["agents"]
        if not result.get("complete", True):
            print(f"note: {env_id}: incomplete run, skipped", file=sys.stderr)
            continue
        base_time = agents[baseline].get("decision_seconds_mean")
        for spec, res in agents.items():
            name, options = parse_spec(spec)
            record = None if options else _record_for(name, env_id)
            if record is None or spec == baseline:
                continue
            if record.baseline != baseline:
                print(
                    f"note: {env_id} {spec}: run against {baseline}, the record's baseline is "
                    f"{record.baseline}; skipped",
                    file=sys.stderr,
                )
                continue
            paired = res["paired"]
            out.append(
                (
                    record,
                    {
                        "agent": record.name,
                        "env_id": env_id,
                        "env_kwargs": result.get("env_kwargs") or {},
                        "baseline": baseline,
                        "seed": int(result["seed"]),
                        "episodes": int(result["episodes"]),
                        "mean_difference": paired["mean_diff"],
                        "ci95": list(paired["ci95"]),
                        "wins": paired["wins"],
                        "ties": paired["ties"],
                        "losses": paired["losses"],
                        "decision_time_ratio": res["decision_seconds_mean"] / base_time,
                        "command": command,
                        "measured": date,
                        **_reference(agents, spec, baseline),
                    },
                )
            )
    return out


#: the non-myopic reference whose edge a learned policy's is compared with, where it ran
REFERENCE = "rollout"


def share_of_edge(
    returns: np.ndarray, reference: np.ndarray, baseline: np.ndarray, resamples: int = 10_000
) -> tuple[float, tuple[float, float]]:
    """``mean(returns - baseline) / mean(reference - baseline)`` over seeds, with a bootstrap CI.

    The seeds are resampled in pairs (percentile bootstrap, 10,000 resamples, generator seed 0,
    as the bench's intervals are).
    """
    ours, theirs = returns - baseline, reference - baseline
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(ours), size=(resamples, len(ours)))
    ratios = ours[idx].mean(axis=1) / theirs[idx].mean(axis=1)
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(ours.mean() / theirs.mean()), (float(lo), float(hi))


def _reference(agents: dict[str, Any], spec: str, baseline: str) -> dict[str, Any]:
    """The ``reference`` block of a standing: the reference's edge and this agent's share of it."""
    if REFERENCE not in agents or REFERENCE == spec:
        return {}
    ref = agents[REFERENCE]
    share, ci = share_of_edge(
        np.asarray(agents[spec]["returns"], float),
        np.asarray(ref["returns"], float),
        np.asarray(agents[baseline]["returns"], float),
    )
    return {
        "reference": {
            "agent": REFERENCE,
            "mean_difference": ref["paired"]["mean_diff"],
            "ci95": list(ref["paired"]["ci95"]),
            "decision_time_ratio": ref["decision_seconds_mean"]
            / agents[baseline]["decision_seconds_mean"],
            "share_of_edge": share,
            "share_ci95": list(ci),
        }
    }


def _key(entry: dict[str, Any]) -> str:
    return json.dumps([entry["agent"], entry["env_id"], entry["env_kwargs"]], sort_keys=True)


def _timings(paths: list[Path]) -> list[dict[str, Any]]:
    """The ``benchmarks/bench_decision_time.py --json`` files (interleaved decision times)."""
    return [read_metadata(p, what="decision-time JSON") for p in paths]


def with_timing(entry: dict[str, Any], timings: list[dict[str, Any]]) -> dict[str, Any]:
    """``entry`` with its decision-time ratios from an interleaved timing of the same env.

    The bench plays agents one after another, so its ratios move with the machine's load; a
    timing file of the same env, keywords and baseline that has the agent (and the reference)
    replaces them, and the entry records the timing's command.
    """
    for t in timings:
        same = t["env_id"] == entry["env_id"] and t["env_kwargs"] == entry["env_kwargs"]
        agents = t["agents"]
        if not same or t["baseline"] != entry["baseline"] or entry["agent"] not in agents:
            continue
        entry = {
            **entry,
            "decision_time_ratio": agents[entry["agent"]]["ratio"],
            "decision_time_command": t["command"],
        }
        ref = entry.get("reference")
        if ref is not None and ref["agent"] in agents:
            entry["reference"] = {**ref, "decision_time_ratio": agents[ref["agent"]]["ratio"]}
        return entry
    return entry


def record(paths: list[Path], timing: list[Path] | None = None) -> list[str]:
    """Write the standings of the bench JSONs ``paths`` into the checkpoint JSONs; their lines.

    ``timing``: interleaved decision-time files whose ratios replace the bench's
    (:func:`with_timing`).
    """
    by_file: dict[str, list[dict[str, Any]]] = {}
    lines: list[str] = []
    timings = _timings(timing or [])
    for path in paths:
        doc = read_metadata(path, what="bench JSON")
        for rec, entry in standings_of(doc):
            entry = with_timing(entry, timings)
            by_file.setdefault(rec.checkpoint, []).append(entry)
            lines.append(
                f"{rec.checkpoint}: {entry['agent']} on {entry['env_id']} "
                f"{entry['env_kwargs'] or ''} {entry['mean_difference']:+.4g} "
                f"{entry['ci95']}"
            )
    for checkpoint, entries in by_file.items():
        target = checkpoint_dir() / f"{checkpoint.rsplit('.', 1)[0]}.json"
        meta = read_metadata(target)
        kept = {_key(e): e for e in meta.get("standings", [])}
        kept.update({_key(e): e for e in entries})
        meta["standings"] = sorted(kept.values(), key=lambda e: (e["env_id"], e["agent"], _key(e)))
        write_json(target, meta)
    read_standings.cache_clear()
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bench_json", nargs="+", type=Path, help="JSON files of selenv bench")
    parser.add_argument(
        "--timing",
        nargs="+",
        type=Path,
        default=[],
        help="benchmarks/bench_decision_time.py --json files: their interleaved decision-time "
        "ratios replace the bench's",
    )
    args = parser.parse_args(argv)
    try:
        for line in record(args.bench_json, args.timing):
            print(line)
    except (OSError, ValueError, KeyError) as exc:
        print(f"record_standings: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
