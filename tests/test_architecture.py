"""The layering of the package, enforced: the numerical rooms stay free of I/O, dependencies point one way."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "online_id"

# What each room may import of the project (besides itself), from the bottom up; imports under
# `if TYPE_CHECKING:` do not count.  A room is a package under online_id/ or a module at its top level; the
# top level holds only what serves all of it.  Every room is listed (test_every_room_has_a_rule).
BASE = {"errors", "records", "units", "progress", "config"}
CORE = {"analysis", "estimation", "monitoring", "diagnose"}
ALLOWED = {
    # the base: serves every room
    "errors": set(),
    "records": set(),
    "units": {"errors"},
    "progress": set(),
    "config": {"errors", "estimation", "monitoring"},  # the identification's settings, detection's defaults
    # the numerical core: no I/O, no clocks
    "analysis": {"errors", "records"},
    "estimation": {"errors", "records", "analysis"},
    "monitoring": {"errors", "records", "analysis"},
    "diagnose": {"errors", "records", "units", "analysis", "estimation"},
    # adapters to files, CAN, MQTT
    "io": {"errors", "records"},
    # the streaming path shared by the live service and replay
    "service": BASE | CORE | {"io"},
    # what reads recordings into samples (a CAN log as the service would)
    "ingest": BASE | CORE | {"io", "service"},
    # the bench simulator and the detection evaluation that drives the pipeline
    "bench": BASE | CORE | {"service"},
    # tables and figures
    "report": BASE | CORE,
    # the work behind the offline commands; the Dask runner of the archive runs evaluations too
    "offline": BASE | CORE | {"io", "service", "ingest", "bench", "report", "archive"},
    # a test centre's archive
    "archive": BASE | CORE | {"io", "service", "ingest", "bench", "report"},
    # the evaluations of the diagnosis on simulated benches and rigs (the chain family: see CHAIN below)
    "evaluation": BASE | CORE | {"io", "bench", "ingest", "offline", "archive"},  # archive: the Dask runner
    # the command line on top of everything
    "interrupt": {"io"},
    "cli": None,  # may import every room
    "__main__": {"cli"},
}
CHAIN = {"errors", "records", "bench", "evaluation"}
"""What the chain family's modules (online_id.evaluation.chain*) may import: they judge the diagnosis from outside,
through its command line only, so that nothing of the diagnosis shapes the benches it is judged on."""


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, top_level_only: bool) -> set[str]:
    """Project modules imported by ``path`` (module-level only, if asked; TYPE_CHECKING blocks skipped)."""
    tree = ast.parse(path.read_text(), str(path))
    found: set[str] = set()

    def visit(node: ast.AST, depth: int) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            nested = isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if nested and top_level_only:
                continue
            if isinstance(child, ast.ImportFrom) and child.module and child.module.startswith("online_id"):
                found.add(child.module)
                for alias in child.names:
                    found.add(f"{child.module}.{alias.name}")
            elif isinstance(child, ast.Import):
                found.update(a.name for a in child.names if a.name.startswith("online_id"))
            visit(child, depth + 1)

    visit(tree, 0)
    return found


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _layering_breaks() -> set[str]:
    bad = set()
    for name, path in _modules().items():
        room = _room(name)
        if ALLOWED.get(room, set()) is None:
            continue
        for imp in _imports(path, top_level_only=False):
            target = _room(imp)
            if target and target != room and target not in ALLOWED.get(room, set()) and target != "__version__":
                bad.add(f"{name} imports {imp}")
    return bad


def test_the_chain_family_judges_from_outside():
    bad = set()
    for name, path in _modules().items():
        if name.startswith("online_id.evaluation.chain"):
            for imp in _imports(path, top_level_only=False):
                target = _room(imp)
                if target not in CHAIN or (target == "evaluation" and imp != "online_id.evaluation"
                                                and not imp.startswith("online_id.evaluation.chain")):
                    bad.add(f"{name} imports {imp}")
    assert not bad, "the chain family reaches into the product:\n" + "\n".join(sorted(bad))


def test_every_room_has_a_rule():
    rooms = {_room(name) for name in _modules()} - {""}
    assert rooms - set(ALLOWED) == set(), "rooms without a rule in ALLOWED"
    assert set(ALLOWED) - rooms == set(), "rules of rooms that no longer exist"


def test_rooms_import_only_what_lies_below_them():
    bad = _layering_breaks()
    assert not bad, "layering broken:\n" + "\n".join(sorted(bad))


def test_no_import_cycles_between_modules():
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        deps = set()
        for imp in _imports(path, top_level_only=True):
            while imp and imp not in mods:
                imp = imp.rsplit(".", 1)[0] if "." in imp else ""
            if imp and imp != name and not name.startswith(imp + ".") and not mods[imp].name == "__init__.py":
                deps.add(imp)
        graph[name] = deps
    state: dict[str, int] = {}
    cycles = []

    def walk(node: str, stack: list[str]) -> None:
        state[node] = 1
        for dep in graph.get(node, ()):
            if state.get(dep) == 1:
                cycles.append(" -> ".join(stack[stack.index(dep):] + [dep]) if dep in stack else f"{node} -> {dep}")
            elif dep not in state:
                walk(dep, stack + [dep])
        state[node] = 2

    for n in graph:
        if n not in state:
            walk(n, [n])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_numerical_rooms_do_not_load_io_libraries():
    code = (
        "import sys, online_id.estimation.identification, online_id.estimation.online, online_id.estimation.kalman, "
        "online_id.analysis.poles, online_id.monitoring.detection, online_id.monitoring.tracks, "
        "online_id.monitoring.baseline, online_id.service.pipeline, online_id.bench.simulate; "
        "bad = [m for m in ('can', 'cantools', 'matplotlib', 'online_id.io') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_the_cli_loads_only_what_its_command_needs(tmp_path):
    """``online-id --help`` lists every command without importing one; identifying a bench CSV does not load
    python-can, cantools or asammdf (their import took 1.5 s and 50 MB); a CAN log does."""
    from online_id.cli import SUBCOMMANDS

    csv = tmp_path / "bench.csv"
    t = [k / 1000 for k in range(400)]
    csv.write_text("time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm\n"
                   + "".join(f"{x:.3f},1500,1500,{10 + (k % 7)}\n" for k, x in enumerate(t)))
    heavy = ("can", "cantools", "asammdf", "matplotlib", "scipy")
    probe = (
        "import sys, contextlib, io\n"
        "from online_id.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(io.StringIO()):\n"
        "    try:\n"
        "        rc = main(sys.argv[1:])\n"
        "    except SystemExit as e:\n"
        "        rc = e.code\n"
        "print(rc, out.getvalue().count('\\n') > 0, ' '.join(m for m in %r if m in sys.modules),"
        " ' '.join(m for m in sys.modules if m.startswith('online_id.cli.')), sep='|')\n" % (heavy,)
    )

    def run(*argv: str) -> list[str]:
        res = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, check=True)
        return res.stdout.strip().splitlines()[-1].split("|")

    rc, printed, loaded, modules = run("--help")
    assert rc == "0" and printed == "True" and loaded == "" and modules == ""
    assert all(name in subprocess.run([sys.executable, "-m", "online_id", "--help"], capture_output=True,
                                      text=True).stdout for name in SUBCOMMANDS)
    rc, _printed, loaded, modules = run("identify", str(csv), "--json")
    assert modules.split() == ["online_id.cli.identify"]
    assert not {"can", "cantools", "asammdf", "matplotlib"} & set(loaded.split())
    rc, _printed, loaded, _modules = run("identify", str(tmp_path / "bench.log"))
    assert rc == "2" and {"can", "cantools"} <= set(loaded.split())  # a CAN log (missing): the CAN side loads
