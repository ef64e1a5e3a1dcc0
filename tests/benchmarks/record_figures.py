"""Run a benchmark script and keep what it printed as the figures the documentation shows.

Why: figures copied into a page by hand go stale the day the code changes. The benchmarks page
(``docs/benchmarks.md``) quotes no figure itself; it includes, per script, the file this writes:
the script's own output, the command that printed it, and the machine and date it ran on.
The file also records a digest of the script's source, so ``tests/docs/test_docs_benchmarks.py``
fails when a script was changed and its figures were not recorded again.

Run: python tests/benchmarks/record_figures.py NAME [-- ARGS...]   (e.g. bench_models -- --runs 3)
     python tests/benchmarks/record_figures.py --all               (every script, default arguments)
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
FIGURES = ROOT / "docs" / "benchmarks"
DIGEST_MARK = "<!-- script sha256: "


def script_path(name: str) -> Path:
    return HERE / f"{Path(name).stem}.py"


def figures_path(name: str) -> Path:
    return FIGURES / f"{Path(name).stem}.md"


def script_digest(script: Path) -> str:
    """What the recorded figures were printed by: the script's source, whitespace as written."""
    return hashlib.sha256(script.read_bytes()).hexdigest()


def recorded_digest(figures: Path) -> str | None:
    for line in figures.read_text(encoding="utf-8").splitlines():
        if line.startswith(DIGEST_MARK):
            return line[len(DIGEST_MARK):].split()[0]
    return None


def machine() -> str:
    """The machine in one phrase: CPU model, cores, OS and Python (no host name)."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{model}, {os.cpu_count()} cores, {platform.system()} {platform.release().split('-')[0]}, "
            f"CPython {platform.python_version()}")


def as_markdown(output: str) -> str:
    """Markdown tables stay tables; every other run of lines becomes a text block, as printed."""
    blocks: list[str] = []
    text: list[str] = []

    def flush_text() -> None:
        while text and not text[-1].strip():
            text.pop()
        if text:
            blocks.append("```text\n" + "\n".join(text) + "\n```")
        text.clear()

    table: list[str] = []
    for line in output.rstrip().splitlines():
        if line.startswith("|"):
            flush_text()
            table.append(line)
            continue
        if table:
            blocks.append("\n".join(table))
            table = []
        if line.strip() or text:
            text.append(line)
    flush_text()
    if table:
        blocks.append("\n".join(table))
    return "\n\n".join(blocks)


def page(name: str, args: list[str], output: str, when: datetime.date) -> str:
    command = " ".join(["python", f"tests/benchmarks/{script_path(name).name}", *args])
    return (f"{DIGEST_MARK}{script_digest(script_path(name))} -->\n"
            f"Printed by `{command}` on {when.isoformat()} ({machine()}):\n\n"
            f"{as_markdown(output)}\n")


def write_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


def record(name: str, args: list[str]) -> int:
    script = script_path(name)
    if not script.is_file():
        print(f"record_figures: no benchmark {script.name} in {HERE}", file=sys.stderr)
        return 2
    path = os.environ.get("PYTHONPATH")
    env = {**os.environ, "MPLBACKEND": "Agg",
           "PYTHONPATH": f"{ROOT}{os.pathsep}{path}" if path else str(ROOT)}
    print(f"record_figures: running {script.name} {' '.join(args)}", file=sys.stderr)
    result = subprocess.run([sys.executable, str(script), *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, check=False)
    if result.returncode != 0 or not result.stdout.strip():
        print(f"record_figures: {script.name} failed (exit {result.returncode}); nothing recorded",
              file=sys.stderr)
        return 1
    write_atomically(figures_path(name), page(name, args, result.stdout, datetime.date.today()))
    print(f"record_figures: wrote {figures_path(name).relative_to(ROOT)}", file=sys.stderr)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name", nargs="?", help="the script, e.g. bench_models")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="after --: the script's arguments")
    parser.add_argument("--all", action="store_true", help="every bench_*.py, default arguments")
    ns = parser.parse_args()
    args = ns.args[1:] if ns.args[:1] == ["--"] else ns.args
    if ns.all:
        return max((record(s.stem, []) for s in sorted(HERE.glob("bench_*.py"))), default=0)
    if ns.name is None:
        parser.error("name a script, or --all")
    return record(ns.name, args)


if __name__ == "__main__":
    sys.exit(main())
