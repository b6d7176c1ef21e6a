"""Kernel launches of a compiled XLA GPU program, counted from its optimized HLO text, with no GPU.

At small batches the 2-D walker's step costs its kernel launches more than its arithmetic (an H100
trace at 200 envs: 675 launches and 2.49 ms of device time per step), and only a GPU trace counted
them. XLA's optimized HLO says what launches: every instruction of a computation that runs on the
host's stream (the entry, while bodies and conditions, conditional branches, called computations)
is one kernel, except bookkeeping (parameters, constants, tuples, bitcasts); a fusion is one kernel
whatever it fuses; a while loop with a known trip count runs its body and condition that many times.
For the step at 200 envs compiled for an H200 this gives 663.5 launches per step against the H100
trace's 675.5 (docs/bipedal.md, "Where the launches are").

``count(text)`` walks the entry; ``by_scope`` groups the launches by the JAX scopes in each
instruction's ``op_name`` (``jax.named_scope`` and jitted functions' names), which is how a launch
is traced back to the code. Limits: a while loop without a known trip count counts once (listed in
``unknown_trips``); a conditional counts its largest branch.
"""
from __future__ import annotations

import re
from collections import Counter

# instructions that launch nothing
_FREE = frozenset({"parameter", "constant", "tuple", "get-tuple-element", "bitcast", "after-all",
                   "partition-id", "replica-id", "opt-barrier"})


def computations(text: str) -> tuple[dict[str, list[str]], str]:
    """The HLO module's computations: name -> instruction lines, and the entry's name."""
    comps: dict[str, list[str]] = {}
    cur = entry = None
    for line in text.splitlines():
        if line and not line[0].isspace():
            m = re.match(r"^(ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
            if m:
                cur = m.group(2)
                comps[cur] = []
                if m.group(1):
                    entry = cur
                continue
            if line.startswith("}"):
                cur = None
                continue
        if cur is not None and " = " in line:
            comps[cur].append(line)
    if entry is None:
        raise ValueError("hlo_launches: no ENTRY computation in the text")
    return comps, entry


def opcode(line: str) -> str | None:
    """An instruction line's opcode: the first ``name(`` after its result type (types may nest)."""
    rhs = line.split(" = ", 1)[1]
    depth = i = 0
    while i < len(rhs):
        c = rhs[i]
        if c in "([{":
            depth += 1
        elif c in ")]}":
            depth -= 1
        elif c == " " and depth == 0:
            break
        i += 1
    m = re.match(r"\s*([a-z][a-z0-9\-]*)\(", rhs[i:])
    return m.group(1) if m else None


def _callee(line: str, attr: str) -> str:
    return re.search(attr + r"=%?([\w.\-]+)", line).group(1)


def _branches(line: str) -> list[str]:
    m = re.search(r"branch_computations=\{([^}]*)\}", line)
    if m:
        return [b.strip().lstrip("%") for b in m.group(1).split(",")]
    return [_callee(line, "true_computation"), _callee(line, "false_computation")]


def _walk(comps, name, mult, visit, unknown):
    """Calls ``visit(line, op, times)`` for each launching instruction under ``name``; returns launches."""
    total = 0.0
    for line in comps[name]:
        op = opcode(line)
        if op is None or op in _FREE:
            continue
        if op == "while":
            body, cond = _callee(line, "body"), _callee(line, "condition")
            m = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
            if m is None:
                unknown.append(body)
            n = int(m.group(1)) if m else 1
            total += _walk(comps, body, mult * n, visit, unknown) + _walk(comps, cond, mult * (n + 1), visit, unknown)
        elif op == "conditional":
            counts = [_walk(comps, b, mult, lambda *a: None, unknown) for b in _branches(line)]
            biggest = _branches(line)[counts.index(max(counts))]
            total += _walk(comps, biggest, mult, visit, unknown)
        elif op == "call":
            total += _walk(comps, _callee(line, "to_apply"), mult, visit, unknown)
        else:
            visit(line, op, mult)
            total += mult
    return total


def count(text: str) -> dict:
    """Launches of one run of the program: ``total``, ``by_op`` (opcode -> launches) and
    ``unknown_trips`` (while bodies counted once for want of a known trip count)."""
    comps, entry = computations(text)
    ops: Counter = Counter()
    unknown: list[str] = []
    total = _walk(comps, entry, 1, lambda line, op, n: ops.update({op: n}), unknown)
    return {"total": total, "by_op": dict(ops.most_common()), "unknown_trips": unknown}


def scopes(line: str, depth: int) -> str:
    """The first ``depth`` JAX scopes of an instruction's op_name (``shed_jax.profiling.user_scopes``:
    ``jax.named_scope`` names and jitted functions' names, without the program's own jit, the
    primitive, JAX's structure and jnp's helpers)."""
    from shed_jax.profiling import user_scopes

    m = re.search(r'op_name="([^"]*)"', line)
    return "/".join(user_scopes(m.group(1))[:depth] if m else ()) or "(no scope)"


def by_scope(text: str, depth: int = 2) -> dict[str, float]:
    """Launches of one run of the program grouped by ``scopes(line, depth)``, most first."""
    comps, entry = computations(text)
    where: Counter = Counter()
    _walk(comps, entry, 1, lambda line, op, n: where.update({scopes(line, depth): n}), [])
    return dict(where.most_common())
