"""Size and shape of orthowarp's code: lines per file, the longest function bodies, the most
parameters, type-hint coverage and the import graph's cycles, per top-level folder.

Counts every .py file under orthowarp/, kernels/, pipeline/ and adjust/ of a source tree (the
current checkout, or ``--root`` for another, e.g. a ``git archive`` of an earlier commit).
Kernels and Warp functions are included in the sizes but left out of the type-hint coverage
(their annotations are Warp types, required by Warp). An import cycle is a strongly connected
set of modules, imports inside functions included.

usage: python3 bench/code_metrics.py [--root DIR] [--out FILE]
"""

import argparse
import ast
import collections
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402

FOLDERS = ("orthowarp", "kernels", "pipeline", "adjust")
PACKAGE = {"orthowarp": "orthowarp", "kernels": "orthowarp.kernels", "pipeline": "orthowarp.pipeline",
           "adjust": "orthowarp.adjust"}


def modules(root):
    """{dotted module name: path} of the package's modules in the tree at ``root``."""
    found = {}
    for folder in FOLDERS:
        for base, dirs, files in os.walk(os.path.join(root, folder)):
            dirs[:] = [d for d in dirs if not d.startswith((".", "_"))]
            for f in files:
                if f.endswith(".py"):
                    rel = os.path.relpath(os.path.join(base, f), os.path.join(root, folder))[:-3].split(os.sep)
                    if rel[-1] == "__init__":
                        rel = rel[:-1]
                    found[".".join([PACKAGE[folder], *rel])] = os.path.join(base, f)
    return found


def _is_device_code(node):
    for d in node.decorator_list:
        text = ast.unparse(d)
        if text.startswith(("wp.func", "wp.kernel", "warp.func", "warp.kernel", "wp.struct")):
            return True
    return False


def functions(tree):
    """(name, body lines, parameters, fully hinted, device code) of every function."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            params = [*a.posonlyargs, *a.args, *a.kwonlyargs] + [x for x in (a.vararg, a.kwarg) if x is not None]
            named = [p for p in params if p.arg not in ("self", "cls")]
            hinted = all(p.annotation is not None for p in named) and (
                node.returns is not None or node.name == "__init__")
            body = node.body[1:] if (node.body and isinstance(node.body[0], ast.Expr)
                                     and isinstance(getattr(node.body[0], "value", None), ast.Constant)) else node.body
            lines = (body[-1].end_lineno - body[0].lineno + 1) if body else 0
            out.append((node.name, lines, len(named), hinted, _is_device_code(node)))
    return out


def imports(name, path, tree, known):
    """The package modules that module ``name`` imports (anywhere in it)."""
    is_pkg = path.endswith("__init__.py")
    here = name.split(".") if is_pkg else name.split(".")[:-1]
    targets = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = here[:len(here) - node.level + 1] if node.level else []
            mod = ".".join([*base, *([node.module] if node.module else [])]) if node.level else node.module
            for alias in node.names:
                full = f"{mod}.{alias.name}"
                targets.add(full if full in known else mod)
        elif isinstance(node, ast.Import):
            targets.update(a.name for a in node.names)
    return {t for t in targets if t in known and t != name}


def cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def measure(root):
    mods = modules(root)
    trees = {m: ast.parse(open(p, encoding="utf-8").read(), filename=p) for m, p in mods.items()}
    lines = {m: sum(1 for _ in open(p, encoding="utf-8")) for m, p in mods.items()}
    per_folder = collections.defaultdict(lambda: dict(files=0, lines=0, functions=0, hinted=0))
    funcs = []
    for m, tree in trees.items():
        folder = m.split(".")[1] if m.count(".") and m.split(".")[1] in ("kernels", "pipeline", "adjust") else "orthowarp"
        row = per_folder[folder]
        row["files"] += 1
        row["lines"] += lines[m]
        for name, n, params, hinted, device in functions(tree):
            funcs.append(dict(module=m, function=name, body_lines=n, parameters=params))
            if not device:
                row["functions"] += 1
                row["hinted"] += hinted
    for row in per_folder.values():
        row["type_hint_coverage"] = round(row["hinted"] / row["functions"], 3) if row["functions"] else None
    graph = {m: imports(m, mods[m], t, mods) for m, t in trees.items()}
    return dict(
        folders=dict(sorted(per_folder.items())),
        files_over_1000_lines={m: n for m, n in sorted(lines.items(), key=lambda kv: -kv[1]) if n > 1000},
        largest_files=[dict(module=m, lines=n) for m, n in sorted(lines.items(), key=lambda kv: -kv[1])[:10]],
        longest_functions=sorted(funcs, key=lambda f: -f["body_lines"])[:15],
        functions_over_80_lines=sum(f["body_lines"] > 80 for f in funcs),
        most_parameters=sorted(funcs, key=lambda f: -f["parameters"])[:10],
        functions_over_10_parameters=sum(f["parameters"] > 10 for f in funcs),
        import_cycles=cycles(graph),
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    ap.add_argument("--out", default="bench/results/code-metrics.json")
    args = ap.parse_args()
    report = dict(benchmark="code_metrics", root=os.path.abspath(args.root), **measure(args.root))
    save_report(report, args.out)
    for key in ("folders", "files_over_1000_lines", "functions_over_80_lines", "functions_over_10_parameters",
                "import_cycles"):
        print(key, report[key])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
