"""Every metric the Grafana dashboard, the HPAs and the prometheus-adapter rules refer to is
exported by the daemon's /metrics (scraped from a running daemon), with the label values
they select on. The shared-mode metrics of the scale-out overlay's HPA and the adapter's
external rule are exported by a daemon in shared mode only: they are checked against a
shared-mode daemon on a local nats-server where the binary has shared mode and
nats-server is installed, and against the metrics docs/deploy.md documents for shared mode
always."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
import urllib.error
import urllib.request

import pytest
import yaml

from conftest import ROOT, free_port, free_ports
from test_dockerfile import serve_env_vars
from test_k8s import shared_mode_docs

DASHBOARD = ROOT / "deploy" / "grafana" / "mcdenoise-dashboard.json"
ADAPTER = ROOT / "deploy" / "prometheus-adapter" / "rules.yaml"
HPA = ROOT / "deploy" / "k8s" / "base" / "hpa.yaml"
SCALE_OUT_HPA = ROOT / "deploy" / "k8s" / "overlays" / "scale-out" / "hpa-patch.yaml"
# Labels Prometheus adds to every target, not the daemon.
TARGET_LABELS = {"namespace", "pod", "job", "instance", "service", "container", "endpoint", "le"}


def scrape(daemon):
    status, text = daemon.get("/metrics")
    assert status == 200
    series = {}
    suffixes = {"counter": ["_total"], "histogram": ["_bucket", "_sum", "_count"], "gauge": [""]}
    for line in text.splitlines():
        # A family registered without series yet (e.g. gRPC calls before the first call)
        # is still exported: its samples' names follow from its type.
        m = re.match(r"# TYPE (\S+) (\w+)$", line)
        if m:
            for suffix in suffixes.get(m.group(2), [""]):
                series.setdefault(m.group(1) + suffix, [])
        if line and not line.startswith("#"):
            # Label values may hold braces (route="/v1/jobs/{id}").
            m = re.match(r'([a-zA-Z_:][a-zA-Z0-9_:]*)(\{((?:[^"}]|"(?:[^"\\]|\\.)*")*)\})?\s', line)
            assert m, f"cannot parse {line!r}"
            labels = dict(re.findall(r'(\w+)="([^"]*)"', m.group(3) or ""))
            series.setdefault(m.group(1), []).append(labels)
    return series


def dashboard_exprs():
    dash = json.loads(DASHBOARD.read_text())
    exprs = []
    for p in dash["panels"]:
        exprs += [t["expr"] for t in p.get("targets", [])]
    exprs += [v["definition"] for v in dash["templating"]["list"] if v.get("definition")]
    return exprs


def references(expr):
    """(metric, {label: value}) for each mcdenoise series selector in a PromQL expression."""
    out = []
    for m in re.finditer(r"\b(mcdenoise_[a-z0-9_]+)(\{([^}]*)\})?", expr):
        labels = dict(re.findall(r'(\w+)\s*=\s*"([^"]*)"', m.group(3) or ""))
        out.append((m.group(1), labels))
    return out


def check(series, exprs):
    seen = 0
    for expr in exprs:
        for name, labels in references(expr):
            seen += 1
            assert name in series, f"{name} (in {expr!r}) is not exported"
            wanted = {k: v for k, v in labels.items() if k not in TARGET_LABELS}
            assert any(wanted.items() <= s.items() for s in series[name]), f"no {name} with {wanted}"
    return seen


def test_dashboard_is_well_formed():
    dash = json.loads(DASHBOARD.read_text())
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))
    variables = {v["name"] for v in dash["templating"]["list"]}
    for p in dash["panels"]:
        if p["type"] == "row":
            continue
        assert p["targets"] and p["datasource"]["uid"] == "${datasource}"
        for t in p["targets"]:
            for v in re.findall(r"\$(\w+)", t["expr"]):
                assert v in variables or v.startswith("__"), v
    titles = " ".join(p["title"].lower() for p in dash["panels"])
    for topic in ("queue depth", "jobs finished", "stage latency", "failed"):
        assert topic in titles


def exercise(daemon, tmp_path):
    """One job over each transport: the request counters get their first series
    (`mcdenoise_grpc_requests_total` has none before the first gRPC call)."""
    import mcdenoise_client as mc
    from conftest import FRAMES, TOKEN, mcdenoise_bin
    mc.Client(daemon.url, token=TOKEN).denoise(FRAMES / "cornell-spp8.exr", tmp_path / "http.exr")
    r = subprocess.run([str(mcdenoise_bin()), "submit", str(FRAMES / "cornell-spp8.exr"), "--server",
                        f"grpc://127.0.0.1:{daemon.grpc_port}", "--token", TOKEN, "--quiet", "-o", str(tmp_path / "grpc.exr")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def shared_mode_exprs():
    """The scale-out overlay's references: the adapter's external rules and its HPA."""
    external = yaml.safe_load(ADAPTER.read_text())["externalRules"]
    hpa = yaml.safe_load(SCALE_OUT_HPA.read_text())
    return ([r["seriesQuery"] for r in external] + [r["metricsQuery"] for r in external]
            + [m["external"]["metric"]["name"] for m in hpa["spec"]["metrics"]])


def test_every_metric_referenced_is_exported(daemon, tmp_path):
    exercise(daemon, tmp_path)
    series = scrape(daemon)
    assert check(series, dashboard_exprs()) >= 25
    rules = yaml.safe_load(ADAPTER.read_text())["rules"]
    check(series, [r["seriesQuery"] for r in rules] + [r["metricsQuery"] for r in rules])
    hpa = yaml.safe_load(HPA.read_text())
    for m in hpa["spec"]["metrics"]:
        assert m["pods"]["metric"]["name"] in series
    # The HPA's metric is the queue gauge, one series per priority class.
    assert {s["priority"] for s in series["mcdenoise_queue_depth"]} == {"high", "normal", "low"}
    # This daemon runs embedded: the scale-out overlay's metrics must be exported, or be
    # shared-mode metrics that docs/deploy.md documents (exported in shared mode only;
    # test_shared_mode_exports_its_metrics scrapes them where it can).
    documented = shared_mode_docs()["metrics"]
    assert {"mcdenoise_shared_queue_messages", "mcdenoise_nats_connected"} <= documented
    assert check({**{name: [{}] for name in documented}, **series}, shared_mode_exprs()) >= 3


def start_nats(tmp_path):
    """A local nats-server with JetStream on loopback ports; (process, client port)."""
    port, monitor = free_ports(2)
    log = open(tmp_path / "nats.log", "wb")
    proc = subprocess.Popen([shutil.which("nats-server"), "-js", "-a", "127.0.0.1", "-p", str(port), "-m", str(monitor),
                             "-sd", str(tmp_path / "js")], stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        assert proc.poll() is None, (tmp_path / "nats.log").read_text()
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{monitor}/healthz", timeout=2):
                return proc, port
        except (urllib.error.URLError, OSError):
            time.sleep(0.1)
    proc.kill()
    raise AssertionError("nats-server did not become healthy")


def test_shared_mode_exports_its_metrics(make_daemon, tmp_path):
    if "MCDENOISE_STORE" not in serve_env_vars():
        pytest.skip("mcdenoise serve has no shared mode yet (no MCDENOISE_STORE)")
    if not shutil.which("nats-server"):
        pytest.skip("nats-server is not installed")
    nats, port = start_nats(tmp_path)
    version = subprocess.run([shutil.which("nats-server"), "--version"], capture_output=True, text=True).stdout.strip()
    try:
        try:
            d = make_daemon("--store", f"nats://127.0.0.1:{port}")
        except AssertionError as e:
            # docs/deploy.md promises nats-server 2.9 or newer.
            raise AssertionError(f"shared mode on {version}: {e}") from None
        series = scrape(d)
        for name in shared_mode_docs()["metrics"]:
            assert name in series, f"{name} (docs/deploy.md) is not exported in shared mode"
        check(series, shared_mode_exprs())
        assert {s["priority"] for s in series["mcdenoise_queue_depth"]} == {"high", "normal", "low"}
        d.stop()
    finally:
        nats.terminate()
        nats.wait(30)


def test_the_check_catches_an_unknown_metric(daemon):
    series = scrape(daemon)
    with pytest.raises(AssertionError):
        check(series, ['sum(rate(mcdenoise_jobs_done_total[5m]))'])
    with pytest.raises(AssertionError):
        check(series, ['mcdenoise_jobs_finished_total{outcome="exploded"}'])
