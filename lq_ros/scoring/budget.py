"""Budget attribution: whether a timeout under the paper's budget (``budget_counts`` ``all``) was decided by the
budget (hold ticks spent it) or by the policy, and each cell's budget mark.

- :func:`add_budget_attribution`: per episode, the action-budget twin's outcome and the attribution.
- :func:`add_budget_counts`: per cell, the counts and ``budget_mark`` ("decided", "proxy" or "").
- :func:`budget_note`: the text the report prints for a cell.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from lq_ros.scoring.intervals import wilson_interval
from lq_ros.scoring.labels import _distinct, _pair_keys, base_labels

#: ``budget_counts`` of rows scored before the choice existed: every tick counted (the paper's budget).
DEFAULT_BUDGET_COUNTS = "all"
#: Fewest timeouts a cell's budget mark rests on: one rescued timeout of two is an anecdote (its rescued fraction's
#: interval is [9%, 91%]).
MIN_TIMEOUTS = 5


def add_budget_attribution(episodes: pd.DataFrame) -> pd.DataFrame:
    """Attribute every timeout under ``budget_counts`` ``all`` to the budget or to the policy.

    Adds per episode:
    - ``budget_twin_success``: for a row under budget ``all``, whether the same episode (variant, protocol,
      latency, suite, task, init, seed) under budget ``action`` succeeded; None without such a row.
    - ``budget_limited``: for a failure under budget ``all``, True when the budget and not the policy decided
      it, False when the policy did, None when the rows cannot tell. The rule, first that applies:
      1. latency 0: False (no inference holds the arm, so the budget was all action ticks);
      2. the action-budget twin exists: its outcome (in lockstep it is this episode continued past the
         budget: a success there means more ticks would have sufficed);
      3. the proxy: the same variant, protocol and pair succeeded at latency 0, and this episode executed fewer
         action ticks (``action_ticks``) than that success needed: True (holds spent the budget before the policy
         had the actions it needs unimpeded). The proxy is necessary, not sufficient (in sync a timeout has about
         B r / (r + N) action ticks by arithmetic, so at large N nearly every timeout passes it): it is never
         applied to an episode whose arm received no fresh action (degenerate protocol) or that had underruns,
         and it never makes a cell "budget-decided" (:func:`add_budget_counts`); otherwise False;
      4. otherwise None.
    - ``budget_basis``: which of the rules gave ``budget_limited`` (``latency 0``, ``action-budget run``,
      ``zero-latency action ticks``).
    """
    out = episodes.copy()
    n = len(out)
    twin_success: list[bool | None] = [None] * n
    limited: list[bool | None] = [None] * n
    basis: list[str | None] = [None] * n
    if n:
        pairs = _pair_keys(out)
        latency = pd.to_numeric(out["latency_s"], errors="coerce").round(9).to_numpy()
        action = pd.to_numeric(out.get("action_ticks"), errors="coerce").to_numpy(dtype=np.float64)
        # Episodes the proxy cannot speak for: no fresh action ran, or the buffer ran dry (underrun holds).
        missing = pd.Series(np.nan, index=out.index)
        fresh = pd.to_numeric(out.get("fresh_actions_executed", missing), errors="coerce").to_numpy(dtype=np.float64)
        underruns = pd.to_numeric(out.get("underrun_ticks", missing), errors="coerce").fillna(0).to_numpy(np.float64)
        degenerate = out.get("degenerate_protocol", pd.Series(False, index=out.index)).fillna(False).astype(bool)
        no_proxy = degenerate.to_numpy() | (fresh == 0) | (underruns > 0)
        status, budget = out["status"].to_numpy(), out["budget_counts"].to_numpy()
        mode, dist = out["mode"].astype(str).to_numpy(), out["latency_dist"].astype(str).to_numpy()
        twin_keys = list(zip(base_labels(out, ("budget_counts",)), mode, latency, dist, pairs, strict=True))
        zero_keys = list(zip(base_labels(out, ("budget_counts", "latency_dist")), mode, pairs, strict=True))
        twins = {
            key: s == "success"
            for key, b, s in zip(twin_keys, budget, status, strict=True)
            if b == "action" and s in ("success", "failure")
        }
        needed: dict[tuple, float] = {}  # zero-latency successes: the fewest action ticks the pair needed
        for key, lat, s, a in zip(zero_keys, latency, status, action, strict=True):
            if lat == 0 and s == "success" and np.isfinite(a):
                needed[key] = min(needed.get(key, math.inf), float(a))
        for i in range(n):
            if budget[i] != DEFAULT_BUDGET_COUNTS:
                continue
            twin_success[i] = twins.get(twin_keys[i])
            if status[i] != "failure":
                continue
            if latency[i] == 0:
                limited[i], basis[i] = False, "latency 0"
            elif not latency[i] > 0:
                continue  # unknown latency: nothing to compare with
            elif twin_success[i] is not None:
                limited[i], basis[i] = twin_success[i], "action-budget run"
            elif zero_keys[i] in needed and np.isfinite(action[i]) and not no_proxy[i]:
                limited[i], basis[i] = bool(action[i] < needed[zero_keys[i]]), "zero-latency action ticks"
    out["budget_twin_success"] = pd.Series(twin_success, index=out.index, dtype=object)
    out["budget_limited"] = pd.Series(limited, index=out.index, dtype=object)
    out["budget_basis"] = pd.Series(basis, index=out.index, dtype=object)
    return out


def add_budget_counts(row: dict, group: pd.DataFrame) -> None:
    """Budget attribution of a group (see :func:`add_budget_attribution`): ``n_budget_limited``,
    ``n_policy_limited`` and ``n_budget_unattributed`` timeouts under budget ``all``; the success of the group's
    action-budget twins (``action_budget_success_rate`` over ``action_budget_n``); and the cell's mark:

    - ``budget_mark`` "decided" (``budget_decided``): at least MIN_TIMEOUTS timeouts (``n_timeouts``), and the
      fraction of them that succeed in their action-budget twin (``budget_decided_n``, the rescued fraction
      ``budget_rescued`` with its Wilson 95% interval ``budget_rescued_ci_lo``/``_hi``; ``budget_twinned_n`` of
      them had a twin, a timeout without one counts as not rescued) is above one half with its whole interval:
      the same episodes, given the ticks the holds took, mostly succeed, and chance does not explain it. Where the
      point is at least half but the interval reaches below, the cell is only *consistent with* a budget-decided
      cell (``budget_consistent``), no mark;
    - "proxy": no twin ran for any episode of the cell, at least MIN_TIMEOUTS timeouts, and at least half pass the
      zero-latency action-ticks proxy (``budget_proxy_n``), in a cell without degenerate episodes or underruns: a
      hint, not a finding;
    - "" otherwise.
    """
    budget = group.get("budget_counts", pd.Series(DEFAULT_BUDGET_COUNTS, index=group.index))
    paper = budget.fillna(DEFAULT_BUDGET_COUNTS) == DEFAULT_BUDGET_COUNTS
    failures = paper & (group["status"] == "failure")
    limited = group.get("budget_limited", pd.Series(None, index=group.index, dtype=object))
    n_limited = sum(1 for v in limited[failures] if v is True or v is np.True_)
    n_policy = sum(1 for v in limited[failures] if v is False or v is np.False_)
    n_failures = int(failures.sum())
    basis = group.get("budget_basis", pd.Series(None, index=group.index, dtype=object))
    twin_of_failure = group.get("budget_twin_success", pd.Series(None, index=group.index, dtype=object))[failures]
    n_twin_decided = sum(1 for v in twin_of_failure if v is True or v is np.True_)
    n_twinned = sum(1 for v in twin_of_failure if _is_flag(v))
    n_proxy = sum(1 for v, b in zip(limited[failures], basis[failures], strict=True)
                  if (v is True or v is np.True_) and b == "zero-latency action ticks")  # fmt: skip
    degenerate = group.get("degenerate_protocol", pd.Series(False, index=group.index)).fillna(False).astype(bool)
    underruns = pd.to_numeric(group.get("underrun_ticks", pd.Series(0, index=group.index)), errors="coerce").fillna(0)
    proxy_allowed = not degenerate.any() and not (underruns > 0).any()
    # Twins of any episode of the cell (a success's too): with one, "no twin run" would be false.
    twins = [bool(v) for v in group.get("budget_twin_success", pd.Series(dtype=object))[paper] if _is_flag(v)]
    rescued_lo, rescued_hi = wilson_interval(n_twin_decided, n_failures) if n_failures else (math.nan, math.nan)
    enough = n_failures >= MIN_TIMEOUTS
    half = n_failures and n_twinned and 2 * n_twin_decided >= n_failures
    if enough and half and rescued_lo > 0.5:
        mark = "decided"
    elif enough and not twins and proxy_allowed and 2 * n_proxy >= n_failures:
        mark = "proxy"
    else:
        mark = ""
    row.update(
        budget_counts=_distinct(budget),
        n_budget_limited=n_limited,
        n_policy_limited=n_policy,
        n_budget_unattributed=n_failures - n_limited - n_policy,
        n_timeouts=n_failures,
        budget_decided_n=n_twin_decided,
        budget_twinned_n=n_twinned,
        budget_proxy_n=n_proxy,
        budget_mark=mark,
        budget_decided=mark == "decided",
        budget_consistent=bool(half) and mark != "decided",
        budget_rescued=n_twin_decided / n_failures if n_failures and n_twinned else math.nan,
        budget_rescued_ci_lo=rescued_lo if n_twinned else math.nan,
        budget_rescued_ci_hi=rescued_hi if n_twinned else math.nan,
    )
    row["action_budget_n"] = len(twins)
    row["action_budget_success_rate"] = sum(twins) / len(twins) if twins else math.nan


def _is_flag(value) -> bool:
    return isinstance(value, bool | np.bool_)


#: Marks a budget-decided cell in tables (figures: a hollow marker); a proxy-only cell (figures: a dotted ring).
BUDGET_MARK = "◇"
PROXY_MARK = "◌"


def budget_note(agg: pd.Series | dict) -> str:
    """What decided an aggregate row's timeouts, with the rescued fraction and its Wilson 95% interval: e.g.
    ``◇ budget-decided by the action-budget twins: 6/6 timeouts succeed under the action budget (100% [61, 100])``,
    ``consistent with a budget-decided cell: 4/6 timeouts succeed under the action budget (67% [30, 90]); the
    interval reaches below half``, ``◌ budget proxy only, no twin run: 5/5 timeouts ran fewer action ticks than the
    0 s success`` (empty without timeouts under the paper budget; ``action budget`` for such a cell)."""
    if agg.get("budget_counts") == "action":
        return "action budget"
    counts = [agg.get(k) for k in ("n_budget_limited", "n_policy_limited", "n_budget_unattributed")]
    if any(c is None or pd.isna(c) for c in counts) or not sum(counts):
        return ""
    mark, timeouts = agg.get("budget_mark"), int(sum(counts))
    rescued = _rescued_text(agg, timeouts)
    if mark == "decided":
        text = f"{BUDGET_MARK} budget-decided by the action-budget twins: {rescued}"
    elif mark == "proxy":
        text = (f"{PROXY_MARK} budget proxy only, no twin run: {int(agg['budget_proxy_n'])}/{timeouts} timeouts ran"
                " fewer action ticks than the 0 s success")  # fmt: skip
    elif rescued and timeouts < MIN_TIMEOUTS:
        text = f"{rescued}: too few timeouts to attribute (a mark needs {MIN_TIMEOUTS})"
    elif rescued and bool(agg.get("budget_consistent")):
        text = f"consistent with a budget-decided cell: {rescued}; the interval reaches below half"
    else:
        text = f"{int(counts[0])}/{timeouts} timeouts budget-limited"
        proxy = agg.get("budget_proxy_n")
        # Counted by the proxy alone (no twin): say so, it is a hint, not a finding.
        by_proxy = int(proxy) if proxy is not None and not pd.isna(proxy) else 0
        notes = [f"{by_proxy} by the proxy alone"] if by_proxy else []
        notes += [f"{int(counts[2])} unattributed"] if counts[2] else []
        notes += ["too few timeouts for a mark"] if timeouts < MIN_TIMEOUTS and (by_proxy or rescued) else []
        text += f" ({'; '.join(notes)})" if notes else ""
    n_twins = agg.get("action_budget_n")
    if n_twins and not pd.isna(n_twins):
        text += f"; action budget: {100 * agg['action_budget_success_rate']:.0f} % of {int(n_twins)}"
    return text


def _rescued_text(agg, timeouts: int) -> str:
    """``K/F timeouts succeed there (R% [lo, hi]) (U without a twin)``: the rescued fraction with its Wilson 95%
    interval; empty when no timeout had an action-budget twin."""
    twinned = agg.get("budget_twinned_n")
    if twinned is None or pd.isna(twinned) or not int(twinned):
        return ""
    k = int(agg.get("budget_decided_n") or 0)
    lo, hi = wilson_interval(k, timeouts)
    share = f"{100 * k / timeouts:.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]"
    text = f"{k}/{timeouts} timeouts succeed under the action budget ({share})"
    untwinned = timeouts - int(twinned)
    return text + (f" ({untwinned} without a twin)" if untwinned > 0 else "")
