"""deploy/k8s: every kustomization renders (kubectl kustomize), every object validates
against the Kubernetes 1.32 schemas (kubernetes-validate, strict, offline), the
ServiceMonitor (a CRD without a bundled schema) is checked explicitly, and the manifests
agree with the daemon and the image (ports, probes, drain deadline, env vars, user)."""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
from pathlib import Path

import kubernetes_validate
import pytest
import yaml

from conftest import ROOT
from test_dockerfile import env_defaults, serve_env_vars

K8S = ROOT / "deploy" / "k8s"
K8S_VERSION = "1.32.0"  # the kubectl of the machine image (v1.32)
KUSTOMIZATIONS = ["base", "overlays/cpu", "overlays/gpu"]
# Kinds without a schema in kubernetes-validate, each with its own check below.
CRD_KINDS = {("monitoring.coreos.com/v1", "ServiceMonitor")}
EXPECTED_KINDS = {"StatefulSet", "Service", "PodDisruptionBudget", "HorizontalPodAutoscaler", "ServiceMonitor"}


def kubectl() -> str:
    exe = shutil.which("kubectl") or "/usr/bin/kubectl"
    assert Path(exe).is_file(), "kubectl (with kustomize) is part of the machine image"
    return exe


def render(kustomization: str) -> list:
    r = subprocess.run([kubectl(), "kustomize", str(K8S / kustomization)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return [d for d in yaml.safe_load_all(r.stdout) if d]


@pytest.fixture(scope="module", params=KUSTOMIZATIONS)
def objects(request):
    return render(request.param)


def one(objs, kind, name=None):
    found = [o for o in objs if o["kind"] == kind and (name is None or o["metadata"]["name"] == name)]
    assert len(found) == 1, (kind, name, [o["metadata"]["name"] for o in found])
    return found[0]


def validate(obj):
    kubernetes_validate.validate(obj, K8S_VERSION, strict=True)


def test_every_object_validates_against_the_schemas(objects):
    assert {o["kind"] for o in objects} == EXPECTED_KINDS
    for o in objects:
        if (o["apiVersion"], o["kind"]) in CRD_KINDS:
            continue  # test_service_monitor_matches_the_service
        validate(o)


def test_the_validator_is_strict(objects):
    sts = copy.deepcopy(one(objects, "StatefulSet"))
    sts["spec"]["template"]["spec"]["containers"][0]["livenessProbe"]["httpGett"] = {"path": "/livez"}
    with pytest.raises(kubernetes_validate.ValidationError):
        validate(sts)
    hpa = copy.deepcopy(one(objects, "HorizontalPodAutoscaler"))
    hpa["spec"]["metrics"][0]["pods"]["target"]["averageVal"] = "4"
    with pytest.raises(kubernetes_validate.ValidationError):
        validate(hpa)


def test_example_secret_validates_and_holds_the_keys_the_manifests_use(objects):
    secret = yaml.safe_load((K8S / "secret.example.yaml").read_text())
    validate(secret)
    keys = set(secret["stringData"])
    sts = one(objects, "StatefulSet")
    refs = [e["valueFrom"]["secretKeyRef"] for c in sts["spec"]["template"]["spec"]["containers"]
            for e in c.get("env", []) if "valueFrom" in e]
    assert refs and all(r["name"] == secret["metadata"]["name"] and r["key"] in keys for r in refs)
    sm = one(objects, "ServiceMonitor")
    cred = sm["spec"]["endpoints"][0]["authorization"]["credentials"]
    assert cred["name"] == secret["metadata"]["name"] and cred["key"] in keys


def test_service_monitor_matches_the_service(objects):
    sm = one(objects, "ServiceMonitor")
    assert (sm["apiVersion"], sm["kind"]) == ("monitoring.coreos.com/v1", "ServiceMonitor")
    assert set(sm) == {"apiVersion", "kind", "metadata", "spec"}
    assert set(sm["spec"]) <= {"selector", "endpoints", "namespaceSelector", "jobLabel"}
    sel = sm["spec"]["selector"]["matchLabels"]
    services = [s for s in objects if s["kind"] == "Service" and sel.items() <= s["metadata"]["labels"].items()]
    # Exactly the API Service: the headless one would scrape every pod a second time.
    assert [s["metadata"]["name"] for s in services] == ["mcdenoise"]
    port_names = {p["name"] for p in services[0]["spec"]["ports"]}
    assert sm["spec"]["endpoints"]
    for ep in sm["spec"]["endpoints"]:
        assert set(ep) <= {"port", "path", "interval", "scrapeTimeout", "authorization", "scheme"}
        assert ep["port"] in port_names and ep["path"] == "/metrics"
        assert ep["authorization"]["type"] == "Bearer"
        for d in ("interval", "scrapeTimeout"):
            assert re.fullmatch(r"\d+(ms|s|m|h)", ep[d])
    if "namespace" in sm["metadata"]:
        assert sm["metadata"]["namespace"] == services[0]["metadata"].get("namespace")


def test_services_and_probes_match_the_daemon(objects):
    env = env_defaults()
    sts = one(objects, "StatefulSet")
    pod = sts["spec"]["template"]
    c = pod["spec"]["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in c["ports"]}
    port = {name: int(env[var].rsplit(":", 1)[1]) for name, var in
            [("http", "MCDENOISE_HTTP"), ("grpc", "MCDENOISE_GRPC"), ("probe", "MCDENOISE_PROBE_HTTP")]}
    assert ports == port
    # Probes go to the probe listener, which a flood of the API ports cannot starve.
    assert c["startupProbe"]["httpGet"] == {"path": "/livez", "port": "probe"}
    assert c["livenessProbe"]["httpGet"] == {"path": "/livez", "port": "probe"}
    assert c["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "probe"}
    # The router is built from these tables (src/http/mod.rs); the probes must be open.
    routes = (ROOT / "src" / "http" / "mod.rs").read_text()
    open_routes = routes.split("pub const OPEN_ROUTES")[1].split(";")[0]
    protected = routes.split("pub const PROTECTED_ROUTES")[1].split("];")[0]
    assert '("GET", "/livez")' in open_routes and '("GET", "/readyz")' in open_routes
    assert '("GET", "/metrics")' in protected
    for svc in (o for o in objects if o["kind"] == "Service"):
        assert svc["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
        for p in svc["spec"]["ports"]:
            assert p["targetPort"] in ports
    assert sts["spec"]["serviceName"] == one(objects, "Service", "mcdenoise-headless")["metadata"]["name"]
    pdb = one(objects, "PodDisruptionBudget")
    assert pdb["spec"]["selector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    # The data volume is where the image keeps the job store.
    mounts = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}
    assert mounts["data"] == env["MCDENOISE_DATA_DIR"]
    assert [t["metadata"]["name"] for t in sts["spec"]["volumeClaimTemplates"]] == ["data"]
    # The image's user.
    assert pod["spec"]["securityContext"]["runAsUser"] == 10001 and pod["spec"]["securityContext"]["runAsNonRoot"]


def duration_s(s: str) -> float:
    m = re.fullmatch(r"(\d+)(ms|s|m|h)", s)
    return int(m.group(1)) * {"ms": 1e-3, "s": 1, "m": 60, "h": 3600}[m.group(2)]


def test_termination_grace_outlasts_the_drain(objects):
    server = (ROOT / "src" / "server.rs").read_text()
    grace = {k: int(v) for k, v in re.findall(r"const (WORKER_GRACE|TRANSPORT_GRACE): Duration = Duration::from_secs\((\d+)\)", server)}
    assert set(grace) == {"WORKER_GRACE", "TRANSPORT_GRACE"}
    sts = one(objects, "StatefulSet")
    c = sts["spec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e.get("value") for e in c["env"]}
    timeout = duration_s(env.get("MCDENOISE_SHUTDOWN_TIMEOUT") or env_defaults()["MCDENOISE_SHUTDOWN_TIMEOUT"])
    # The daemon's bound (src/server.rs `run`): the shutdown timeout, WORKER_GRACE for
    # running jobs to stop at a tile, WORKER_GRACE to join the workers, TRANSPORT_GRACE.
    drain = timeout + 2 * grace["WORKER_GRACE"] + grace["TRANSPORT_GRACE"]
    assert sts["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] > drain


def test_env_vars_are_options_of_the_daemon(objects):
    known = serve_env_vars()
    c = one(objects, "StatefulSet")["spec"]["template"]["spec"]["containers"][0]
    names = [e["name"] for e in c["env"]]
    assert set(names) <= known, set(names) - known
    assert len(names) == len(set(names))
    for e in c["env"]:
        if e["name"] in ("MCDENOISE_SHUTDOWN_TIMEOUT", "MCDENOISE_RESULT_TTL"):
            duration_s(e["value"])
    assert c["resources"]["requests"]["cpu"] and c["resources"]["requests"]["memory"]
    assert "memory" in c["resources"]["limits"]


def test_overlays_size_workers_to_the_cpu_request():
    for o in ["overlays/cpu", "overlays/gpu"]:
        c = one(render(o), "StatefulSet")["spec"]["template"]["spec"]["containers"][0]
        env = {e["name"]: e.get("value") for e in c["env"]}
        threads = int(env["MCDENOISE_WORKERS"]) * int(env["MCDENOISE_THREADS_PER_WORKER"])
        assert threads == int(c["resources"]["requests"]["cpu"]), o
        assert one(render(o), "Service", "mcdenoise")["metadata"]["namespace"] == "mcdenoise"


def test_hpa_scales_the_statefulset_on_the_adapter_metric(objects):
    hpa = one(objects, "HorizontalPodAutoscaler")
    sts = one(objects, "StatefulSet")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "StatefulSet", "name": sts["metadata"]["name"]}
    (metric,) = hpa["spec"]["metrics"]
    rules = yaml.safe_load((ROOT / "deploy" / "prometheus-adapter" / "rules.yaml").read_text())["rules"]
    served = {r["name"]["as"] for r in rules}
    assert metric["type"] == "Pods" and metric["pods"]["metric"]["name"] in served
    for r in rules:
        assert set(r["resources"]["overrides"]) == {"namespace", "pod"}
        assert "<<.LabelMatchers>>" in r["metricsQuery"] and "<<.GroupBy>>" in r["metricsQuery"]
