"""An import-linter contract type of this project's (``make lint``): no import cycle between
files.

import-linter's own ``acyclic_siblings`` checks cycles between the siblings of a package;
a module that imports its own package's ``__init__`` while that ``__init__`` imports it (a
child and its parent) is a cycle it does not look at. This one looks at every module (file)
of the root packages, imports inside functions included, and reports each cycle with one
chain that closes it.
"""

from __future__ import annotations

import grimp
from importlinter import Contract, ContractCheck, output


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    modules = sorted(graph.modules)
    edges = {m: sorted(set(graph.find_modules_directly_imported_by(m)) & graph.modules)
             for m in modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in modules:
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            v, i = work.pop()
            if i == 0:
                index[v] = low[v] = len(index)
                stack.append(v)
                on_stack.add(v)
            if i < len(edges[v]):
                work.append((v, i + 1))
                w = edges[v][i]
                if w not in index:
                    work.append((w, 0))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


class AcyclicModulesContract(Contract):
    """``type = "acyclic_modules"``: no module imports, directly or not, a module that
    imports it back."""

    def check(self, graph: grimp.ImportGraph, verbose: bool) -> ContractCheck:
        chains = []
        for component in _cycles(graph):
            first, second = component[0], None
            for m in component[1:]:
                if graph.direct_import_exists(importer=first, imported=m):
                    second = m
                    break
            second = second or component[1]
            back = graph.find_shortest_chain(importer=second, imported=first) or ()
            chains.append({"modules": component, "chain": [first, *back]})
        return ContractCheck(kept=not chains, metadata={"cycles": chains})

    def render_broken_contract(self, check: ContractCheck) -> None:
        for cycle in check.metadata["cycles"]:
            output.print_error(" -> ".join(cycle["chain"]), bold=False)
            output.new_line()
