"""pytest plugin: tests marked ``@pytest.mark.vcan`` run on a real SocketCAN vcan interface.

Why: the service talks to the kernel's CAN stack, and its tests must too, but the kernel of the
development and CI machines has no SocketCAN (see ``tests/support/vcan_harness.py``). Where the vcan
tests run is decided once per session, and only if vcan tests are selected:

``native``
    The host has SocketCAN with ``vcan0`` up (created if root), or this process already runs
    inside a User-mode Linux guest (``CANICAL_IN_UML=1``): vcan tests simply run.
``uml``
    No host vcan, but UML is installed. Collection is unchanged; afterwards each selected vcan
    item is swapped for a :class:`GuestProxyItem` with the same node id. The first proxy to run
    boots ONE guest which runs pytest on exactly those node ids (``-p no:cacheprovider``,
    JUnit XML in the run dir); inside, this plugin writes every test report as a JSON line.
    Each proxy then reports its test's guest outcome: passed, failed with the guest's
    traceback and captured output, skipped/xfailed with the guest's reason.
``missing``
    Neither: the vcan tests FAIL with an explanation (a silent skip would hide that the CAN
    code went untested), unless ``CANICAL_ALLOW_NO_VCAN=1``, which turns that into a skip.

Tests also marked ``@pytest.mark.systemd_guest`` need a real systemd as PID 1 (they start the
units, read the journal): they always go to a second guest, booted with the host's systemd
(:func:`vcan_harness.run_in_uml` with ``systemd=True``), where pytest runs as a oneshot unit
after ``multi-user.target``. Before it boots, the host builds the canical wheel and the
dependencies' wheels (the guest has no network) for the install test; see
``tests/support/systemd_guest.py``.

The guests run **beside the host's tests**: once collection has decided what goes to them, one
background thread boots the vcan guest, then the systemd guest, while the host runs its own
tests; the proxies are moved to the end of the run and wait there for their guest's results
(the guests take one CPU, the host's tests the other). ``CANICAL_GUESTS_IN_BACKGROUND=0`` runs
each guest at its first proxy instead, as before.

``CANICAL_VCAN_MODE=native|uml`` forces a mode (e.g. to exercise the UML path on a machine
that has vcan). ``CANICAL_UML_TIMEOUT`` bounds the guest run (seconds, default 1800);
``CANICAL_UML_KEEP=1`` keeps the guest's run dir even when everything passed.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

try:  # imported as a top-level module (conftest's rootdir on sys.path) or as tests.vcan_plugin
    from support import systemd_guest
    from support import vcan_harness as harness
except ImportError:  # pragma: no cover - depends on how pytest was started
    from tests.support import systemd_guest  # type: ignore[no-redef]
    from tests.support import vcan_harness as harness  # type: ignore[no-redef]

MARK = "vcan"
SELFTEST_MARK = "uml_selftest"
SYSTEMD_MARK = "systemd_guest"
ENV_ALLOW_NO_VCAN = "CANICAL_ALLOW_NO_VCAN"
ENV_MODE = "CANICAL_VCAN_MODE"
ENV_TIMEOUT = "CANICAL_UML_TIMEOUT"
ENV_KEEP = "CANICAL_UML_KEEP"
ENV_BACKGROUND = "CANICAL_GUESTS_IN_BACKGROUND"
#: Set for the guest's pytest: where this plugin appends one JSON line per test report.
ENV_REPORT = "CANICAL_UML_REPORT"

_STATE_KEY = pytest.StashKey["VcanState"]()
_SYSTEMD_STATE_KEY = pytest.StashKey["VcanState"]()


def in_uml_guest() -> bool:
    """True inside a guest started by :func:`vcan_harness.run_in_uml`."""
    return os.environ.get(harness.ENV_IN_UML) == "1"


def needs_systemd(item: pytest.Item) -> bool:
    """Whether ``item`` must run under the systemd guest."""
    return item.get_closest_marker(SYSTEMD_MARK) is not None


def needs_vcan(item: pytest.Item) -> bool:
    """Whether ``item`` must run where vcan exists (marked directly or via class/module).

    Items also marked ``uml_selftest`` start their own guest from the host, so they stay put.
    """
    return (item.get_closest_marker(MARK) is not None
            and item.get_closest_marker(SELFTEST_MARK) is None)


# --------------------------------------------------------------------------------------------
# Guest side: record reports for the host
# --------------------------------------------------------------------------------------------


def report_to_json(report: pytest.TestReport) -> dict[str, Any]:
    """The parts of a test report the host needs to reproduce the outcome, as plain JSON."""
    skip_reason = None
    if report.skipped and isinstance(report.longrepr, tuple):
        skip_reason = str(report.longrepr[2]).removeprefix("Skipped: ")
    crash = getattr(report.longrepr, "reprcrash", None) if report.failed else None
    return {
        "nodeid": report.nodeid,
        "crash": getattr(crash, "message", None),
        "when": report.when,
        "outcome": report.outcome,
        "longrepr": report.longreprtext if report.failed else "",
        "sections": [list(s) for s in report.sections] if report.failed else [],
        "skip_reason": skip_reason,
        "wasxfail": getattr(report, "wasxfail", None),
        "duration": report.duration,
    }


@dataclass
class GuestOutcome:
    """The verdict for one node id, distilled from its guest reports (setup/call/teardown)."""

    outcome: str  # "passed" | "failed" | "skipped" | "xfailed" | "missing"
    message: str = ""
    duration: float = 0.0


def summarize_reports(reports: list[dict[str, Any]]) -> GuestOutcome:
    """Collapse a node id's guest reports into what the host item must report.

    A failure in any phase wins (with the phase named, like pytest's "ERROR at setup"); then
    xfail, then skip; a pass needs a passed call phase.
    """
    duration = sum(float(r.get("duration") or 0.0) for r in reports)
    failed = [r for r in reports if r["outcome"] == "failed"]
    if failed:
        # The first line is what pytest's short summary shows: make it the guest's error.
        first = failed[0].get("crash") or "failed"
        chunks = [f"{first.splitlines()[0] if first.strip() else 'failed'} "
                  f"[in UML guest, {failed[0]['when']} phase]"]
        for r in failed:
            chunks.append(f"----- guest {r['when']} -----\n{r['longrepr']}")
            chunks += [f"----- {title} -----\n{text}" for title, text in r["sections"]]
        return GuestOutcome("failed", "\n".join(chunks), duration)
    for r in reports:
        if r["outcome"] == "skipped" and r.get("wasxfail") is not None:
            return GuestOutcome("xfailed", r["wasxfail"], duration)
    for r in reports:
        if r["outcome"] == "skipped":
            return GuestOutcome("skipped", r.get("skip_reason") or "skipped in UML guest",
                                duration)
    if any(r["when"] == "call" and r["outcome"] == "passed" for r in reports):
        return GuestOutcome("passed", "", duration)
    return GuestOutcome("missing", "the UML guest reported no result for this test", duration)


def read_report_lines(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Group the guest's JSON lines by node id; a truncated last line (killed guest) is skipped."""
    by_node: dict[str, list[dict[str, Any]]] = {}
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return by_node
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        by_node.setdefault(entry["nodeid"], []).append(entry)
    return by_node


# --------------------------------------------------------------------------------------------
# Host side: one guest run per session
# --------------------------------------------------------------------------------------------


class GuestTestFailure(Exception):
    """A vcan test failed in the guest (or the guest failed); the message is the full report."""


@dataclass
class VcanState:
    """Per-session decisions and the (lazily produced) guest results."""

    config: pytest.Config
    systemd: bool = False  # boot systemd in the guest (the systemd_guest tier)
    mode: str | None = None
    reason: str = ""
    nodeids: list[str] = field(default_factory=list)
    result: harness.GuestResult | None = None
    error: str | None = None
    outcomes: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    done: threading.Event | None = None  # set when a background run has finished (None: no background run)

    def decide_mode(self) -> str:
        """Pick native/uml/missing once; probing may create vcan0 on a capable root host."""
        if self.mode is not None:
            return self.mode
        if self.systemd:  # only a guest of ours has a systemd the tests may drive
            problem = harness.uml_unavailable_reason()
            self.mode = "uml" if problem is None else "missing"
            self.reason = ("systemd in a User-mode Linux guest" if problem is None else
                           f"the systemd tests need User-mode Linux: {problem}")
            return self.mode
        forced = os.environ.get(ENV_MODE, "").strip().lower()
        if in_uml_guest() or forced == "native":
            self.mode, self.reason = "native", "forced/inside UML guest"
            return self.mode
        status = harness.host_vcan_status()
        uml_problem = harness.uml_unavailable_reason()
        if status.usable and forced != "uml":
            self.mode, self.reason = "native", status.reason
        elif uml_problem is None:
            self.mode, self.reason = "uml", f"{status.reason}; using a User-mode Linux guest"
        else:
            self.mode = "missing"
            self.reason = (f"vcan tests need SocketCAN, but {status.reason}, and User-mode Linux "
                           f"is unavailable: {uml_problem}")
        return self.mode

    def guest_command(self, run_dir: Path) -> list[str]:
        """pytest, inside the guest, on exactly the selected vcan node ids."""
        config = self.config
        cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-rA", "--color=no",
               f"--junitxml={run_dir / 'junit.xml'}", f"--rootdir={config.rootpath}"]
        if config.inipath is not None:
            cmd += ["-c", str(config.inipath)]
        return cmd + self.nodeids

    def ensure_guest_ran(self) -> None:
        """Boot the guest on first use; later calls reuse its results."""
        if self.result is not None or self.error is not None:
            return
        run_dir = Path(tempfile.mkdtemp(prefix="canical-uml-"))
        report_path = run_dir / "reports.jsonl"
        env = dict(os.environ, **{ENV_REPORT: str(report_path)})
        timeout = float(os.environ.get(ENV_TIMEOUT, harness.DEFAULT_TIMEOUT))
        announce(self.config, f"vcan: booting a User-mode Linux guest for {len(self.nodeids)} vcan test(s); "
                 f"they run in it (several minutes, bound {timeout:.0f} s) and report here when it is done")
        try:
            if self.systemd:
                env.update(systemd_guest.prepare_packages(run_dir))
            self.result = harness.run_in_uml(self.guest_command(run_dir),
                                             cwd=self.config.rootpath, env=env,
                                             timeout=timeout, run_dir=run_dir,
                                             systemd=self.systemd)
        except harness.UmlUnavailable as exc:
            self.error = str(exc)
        except Exception as exc:  # e.g. the kernel binary cannot be executed
            self.error = f"starting the UML guest failed: {exc!r}"
        if self.error is not None:
            shutil.rmtree(run_dir, ignore_errors=True)
            return
        self.outcomes = read_report_lines(report_path)

    def outcome_for(self, nodeid: str) -> GuestOutcome:
        """The guest's verdict for ``nodeid``; guest-level trouble becomes a failure."""
        if self.done is not None:
            self.done.wait()
        self.ensure_guest_ran()
        if self.error is not None:
            return GuestOutcome("failed", self.error)
        assert self.result is not None
        verdict = summarize_reports(self.outcomes.get(nodeid, []))
        if verdict.outcome == "missing":
            verdict.outcome = "failed"
            # The full guest output is printed once, in the terminal summary.
            verdict.message = (f"{verdict.message}: {self.result.headline()}\n"
                               "(guest output: see 'UML guest output' in the summary below)")
        return verdict

    def cleanup(self) -> bool:
        """Delete the run dir unless the guest's pytest failed or keeping was asked; True if kept.

        A kept run dir holds init.sh, console.log, stdout/stderr, junit.xml and reports.jsonl.
        """
        if self.result is None:
            return False
        keep = os.environ.get(ENV_KEEP) == "1" or self.result.returncode != 0
        if not keep:
            shutil.rmtree(self.result.run_dir, ignore_errors=True)
        return keep


def announce(config: pytest.Config, line: str) -> None:
    """One line on the terminal now, past output capture: a silent guest run looks like a hang."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    capture = config.pluginmanager.get_plugin("capturemanager")
    if reporter is None:
        return
    with capture.global_and_fixture_disabled() if capture is not None else contextlib.nullcontext():
        reporter.ensure_newline()
        reporter.write_line(line)


class GuestProxyItem(pytest.Item):
    """Stands in on the host for a vcan test that actually runs in the UML guest.

    It has the original's node id, markers and location but no fixtures, so nothing that needs
    SocketCAN is set up on the host; its result is the guest's.
    """

    def __init__(self, *, original: pytest.Item, state: VcanState, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.original = original
        self.state = state
        self.own_markers.extend(original.own_markers)
        self.keywords.update(original.keywords)
        self.user_properties.append(("vcan_mode", state.mode or ""))

    @classmethod
    def wrap(cls, original: pytest.Item, state: VcanState) -> GuestProxyItem:
        """A proxy with the same parent and name, hence the same node id, as ``original``."""
        return cls.from_parent(original.parent, name=original.name, original=original,
                               state=state)

    def runtest(self) -> None:
        """Report the guest's outcome (or the missing-vcan verdict) as this item's own."""
        if self.state.mode == "missing":
            if os.environ.get(ENV_ALLOW_NO_VCAN) == "1":
                pytest.skip(f"{self.state.reason} ({ENV_ALLOW_NO_VCAN}=1)")
            raise GuestTestFailure(
                f"{self.state.reason}\nSet {ENV_ALLOW_NO_VCAN}=1 to skip vcan tests instead.")
        verdict = self.state.outcome_for(self.nodeid)
        self.user_properties.append(("guest_duration", f"{verdict.duration:.3f}"))
        if verdict.outcome == "skipped":
            pytest.skip(verdict.message)
        if verdict.outcome == "xfailed":
            pytest.xfail(verdict.message)
        if verdict.outcome != "passed":
            raise GuestTestFailure(verdict.message)

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException],
                     style: Any = None) -> str | Any:
        """Show the guest's failure text verbatim rather than a host traceback into this file."""
        if isinstance(excinfo.value, GuestTestFailure):
            return str(excinfo.value)
        return super().repr_failure(excinfo, style=style)

    def reportinfo(self) -> tuple[Any, int | None, str]:
        """Point reports at the real test function."""
        return self.original.reportinfo()


# --------------------------------------------------------------------------------------------
# Hooks and fixtures
# --------------------------------------------------------------------------------------------


def pytest_configure(config: pytest.Config) -> None:
    """Register the markers (harmless if pyproject already does) and the session state."""
    config.addinivalue_line("markers", f"{MARK}: needs a real SocketCAN vcan interface")
    config.addinivalue_line(
        "markers", f"{SELFTEST_MARK}: harness self-test that boots its own User-mode Linux guest "
        f"from the host; combine with {MARK} so that -m 'not {MARK}' never boots a guest")
    config.addinivalue_line(
        "markers", f"{SYSTEMD_MARK}: runs under a real systemd booted in a User-mode Linux guest "
        f"(combine with {MARK})")
    config.stash[_STATE_KEY] = VcanState(config)
    config.stash[_SYSTEMD_STATE_KEY] = VcanState(config, systemd=True)


@pytest.hookimpl(trylast=True)  # after -k/-m deselection: only selected tests go to the guest
def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config,
                                  items: list[pytest.Item]) -> None:
    """Swap selected vcan items for guest proxies when the host cannot run them itself."""
    if in_uml_guest() or config.option.collectonly:
        return
    systemd_items = [i for i in items if needs_systemd(i)]
    if systemd_items:
        sd_state = config.stash[_SYSTEMD_STATE_KEY]
        sd_state.decide_mode()
        sd_state.nodeids = [i.nodeid for i in systemd_items]
        items[:] = [GuestProxyItem.wrap(i, sd_state) if needs_systemd(i) else i for i in items]
    vcan_items = [i for i in items if needs_vcan(i) and not isinstance(i, GuestProxyItem)]
    state = config.stash[_STATE_KEY]
    if vcan_items and state.decide_mode() != "native":
        state.nodeids = [i.nodeid for i in vcan_items]
        items[:] = [GuestProxyItem.wrap(i, state) if i in vcan_items else i for i in items]
    if os.environ.get(ENV_BACKGROUND, "1") != "0":
        run_guests_in_background(items, [s for s in (state, config.stash[_SYSTEMD_STATE_KEY])
                                         if s.nodeids and s.mode == "uml"])


def run_guests_in_background(items: list[pytest.Item], states: list[VcanState]) -> None:
    """Boot the guests one after the other in a thread while the host runs its own tests; the
    proxies go last, so the host reaches them when the guests are (nearly) done."""
    if not states:
        return
    items[:] = ([i for i in items if not isinstance(i, GuestProxyItem)]
                + [i for i in items if isinstance(i, GuestProxyItem)])
    for state in states:
        state.done = threading.Event()

    def run_all() -> None:
        for state in states:
            try:
                state.ensure_guest_ran()
            finally:
                assert state.done is not None
                state.done.set()

    threading.Thread(target=run_all, name="uml-guests", daemon=True).start()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Inside the guest: append each report as a JSON line for the host (flushed at once, so a
    killed guest still leaves the results it had)."""
    path = os.environ.get(ENV_REPORT)
    if not path or not in_uml_guest():
        return
    with open(path, "a") as f:
        f.write(json.dumps(report_to_json(report)) + "\n")


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int,
                            config: pytest.Config) -> None:
    """Say where vcan tests ran and how long each guest took; show guest output on trouble."""
    for key, kind in ((_STATE_KEY, "vcan"), (_SYSTEMD_STATE_KEY, "systemd")):
        state = config.stash.get(key, None)
        if state is not None and state.mode is not None:
            _summarize_guest(terminalreporter, state, kind)


def _summarize_guest(tr: Any, state: VcanState, kind: str) -> None:
    result = state.result
    if state.mode != "uml" or result is None:
        tr.write_line(f"{kind}: mode {state.mode} ({state.reason})")
        return
    kept = state.cleanup()
    boot = f"{result.boot_duration:.1f} s" if result.boot_duration is not None else "?"
    tr.write_line(f"{kind}: {len(state.nodeids)} test(s) ran in a User-mode Linux guest: "
                  f"{result.duration:.1f} s total, {boot} to vcan up"
                  + (f"; run dir kept: {result.run_dir}" if kept else ""))
    if result.returncode == 1:  # tests failed: the guest's own pytest report says most
        tr.section(f"UML {kind} guest pytest output")
        tr.write_line(result.stdout[-20000:].rstrip())
    elif result.returncode != 0:  # the guest itself failed: show everything, console included
        tr.section(f"UML {kind} guest output")
        tr.write_line(result.describe())


@pytest.fixture
def vcan_channel(request: pytest.FixtureRequest) -> str:
    """The SocketCAN channel for vcan tests: ``vcan0`` (on the host or in the guest)."""
    _require_vcan_mark(request)
    return "vcan0"


@pytest.fixture
def vcan_channels(request: pytest.FixtureRequest) -> tuple[str, str]:
    """Two independent vcan buses, ``vcan0`` and ``vcan1`` (skips if the host lacks vcan1)."""
    _require_vcan_mark(request)
    problem = harness.probe_can_interface("vcan1")
    if problem is not None and not in_uml_guest():
        pytest.skip(f"host vcan1 unavailable: {problem}")
    return ("vcan0", "vcan1")


def _require_vcan_mark(request: pytest.FixtureRequest) -> None:
    """Unmarked tests would run on the host without vcan in UML mode: refuse them early."""
    if request.node.get_closest_marker(MARK) is None:
        pytest.fail(f"{request.node.nodeid} uses a vcan fixture but is not marked "
                    f"@pytest.mark.{MARK}", pytrace=False)

