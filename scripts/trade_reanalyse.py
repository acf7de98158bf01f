"""Rewrite a trade-study folder's derived outputs from its own measurements (trade.json).

The speed ratios, the automatic-settings table, trade.md, trade.csv, trade_pareto.png and
frontier.json are recomputed with the current skyfit.tools.trade code from the measured rows;
nothing is rendered or timed again, and the recorded command and machine stay those of the run.

    .venv/bin/python scripts/trade_reanalyse.py docs/bench_trade
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from skyfit.tools.trade import Scene, TradePlan, _write_trade_outputs, auto_table, speed_ratio_de1


def main(folder: str) -> None:
    d = Path(folder)
    s = json.loads((d / "trade.json").read_text())
    p = dict(s["plan"])
    p["scenes"] = tuple(Scene(**sc) for sc in p["scenes"])
    for k, v in p.items():
        if isinstance(v, list):
            p[k] = tuple(tuple(x) if isinstance(x, list) else x for x in v)
    plan = TradePlan(**p)
    s["speed_ratio"] = speed_ratio_de1(s["table"])
    s["speed_ratio_all_trapezoid"] = speed_ratio_de1(s["table"], outer_rule="trapezoid")
    s["auto"] = auto_table(s)
    _write_trade_outputs(d, plan, s, None)
    print(f"rewrote {d}/trade.md, trade.csv, trade.json, trade_pareto.png, frontier.json from trade.json")


if __name__ == "__main__":
    main(sys.argv[1])
