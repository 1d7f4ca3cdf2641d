"""deploy/k8s: every kustomization renders (kubectl kustomize), every object validates
against the Kubernetes 1.32 schemas (kubernetes-validate, strict, offline), the
ServiceMonitor (a CRD without a bundled schema) is checked explicitly, and the manifests
agree with the daemon and the image (ports, probes, drain deadline, env vars, user).
The scale-out overlay (shared mode on NATS JetStream) is checked for its Deployment,
its NATS cluster and configuration, and its autoscaler's External metric."""

from __future__ import annotations

import copy
import functools
import os
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import kubernetes_validate
import pytest
import yaml

from conftest import ROOT
from test_dockerfile import env_defaults, serve_env_vars

K8S = ROOT / "deploy" / "k8s"
K8S_VERSION = "1.32.0"  # the kubectl of the machine image (v1.32)
KUSTOMIZATIONS = ["base", "overlays/cpu", "overlays/gpu", "overlays/scale-out"]
SCALE_OUT = "overlays/scale-out"
# Kinds without a schema in kubernetes-validate, each with its own check below.
CRD_KINDS = {("monitoring.coreos.com/v1", "ServiceMonitor")}
EXPECTED_KINDS = {"StatefulSet", "Service", "PodDisruptionBudget", "HorizontalPodAutoscaler", "ServiceMonitor"}
# scale-out: the daemon as a Deployment, and the NATS cluster (a StatefulSet, its
# configuration, its NetworkPolicy).
SCALE_OUT_KINDS = EXPECTED_KINDS | {"Deployment", "ConfigMap", "NetworkPolicy"}
EXAMPLE_SECRETS = [K8S / "secret.example.yaml", K8S / "nats-secret.example.yaml"]
ADAPTER_RULES = ROOT / "deploy" / "prometheus-adapter" / "rules.yaml"
DEPLOY_DOC = ROOT / "docs" / "deploy.md"


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


@pytest.fixture(scope="module")
def scale_out():
    return render(SCALE_OUT)


def one(objs, kind, name=None):
    found = [o for o in objs if o["kind"] == kind and (name is None or o["metadata"]["name"] == name)]
    assert len(found) == 1, (kind, name, [o["metadata"]["name"] for o in found])
    return found[0]


def daemon(objs):
    """The daemon's workload: the StatefulSet of the base, or the Deployment of scale-out."""
    found = [o for o in objs if o["kind"] in ("StatefulSet", "Deployment") and o["metadata"]["name"] == "mcdenoise"]
    assert len(found) == 1, [(o["kind"], o["metadata"]["name"]) for o in found]
    return found[0]


def daemon_services(objs):
    return [o for o in objs if o["kind"] == "Service" and o["metadata"]["labels"]["app.kubernetes.io/name"] == "mcdenoise"]


def env_of(container) -> dict:
    return {e["name"]: e for e in container.get("env", [])}


def shared_mode_docs() -> dict:
    """What docs/deploy.md's section "Scale-out" documents of shared mode: the environment
    variables of its options table and the metrics of its metrics table."""
    text = DEPLOY_DOC.read_text()
    section = text.split("\n## Scale-out")[1].split("\n## ")[0]
    return {
        "env": set(re.findall(r"^\| `--[a-z-]+[^|]*\| `(MCDENOISE_[A-Z_]+)` \|", section, re.M)),
        "metrics": set(re.findall(r"^\| `(mcdenoise_[a-z_]+)` \| (?:gauge|counter|histogram) \|", section, re.M)),
    }


@functools.lru_cache(maxsize=1)
def known_env_vars() -> frozenset:
    """The options of `mcdenoise serve`. A binary built before shared mode knows none of
    its variables: then they are taken from docs/deploy.md (the interface the overlay is
    written against), and from the binary as soon as it knows any of them."""
    known = serve_env_vars()
    shared = shared_mode_docs()["env"]
    if not known & shared:
        warnings.warn(f"mcdenoise serve has no shared-mode options yet: {sorted(shared)} checked against docs/deploy.md")
        known |= shared
    return frozenset(known)


def validate(obj):
    kubernetes_validate.validate(obj, K8S_VERSION, strict=True)


def test_every_object_validates_against_the_schemas(objects):
    shared = any(o["kind"] == "Deployment" for o in objects)
    assert {o["kind"] for o in objects} == (SCALE_OUT_KINDS if shared else EXPECTED_KINDS)
    for o in objects:
        if (o["apiVersion"], o["kind"]) in CRD_KINDS:
            continue  # test_service_monitor_matches_the_service
        validate(o)


def test_the_validator_is_strict(objects):
    workload = copy.deepcopy(daemon(objects))
    workload["spec"]["template"]["spec"]["containers"][0]["livenessProbe"]["httpGett"] = {"path": "/livez"}
    with pytest.raises(kubernetes_validate.ValidationError):
        validate(workload)
    hpa = copy.deepcopy(one(objects, "HorizontalPodAutoscaler"))
    metric = hpa["spec"]["metrics"][0]
    metric[metric["type"].lower()]["target"]["averageVal"] = "4"
    with pytest.raises(kubernetes_validate.ValidationError):
        validate(hpa)


def test_example_secret_validates_and_holds_the_keys_the_manifests_use(objects):
    keys = {}
    for path in EXAMPLE_SECRETS:
        secret = yaml.safe_load(path.read_text())
        validate(secret)
        # Empty values: applied unedited, the pods do not start rather than run open.
        assert set(secret["stringData"].values()) == {""}, path
        keys[secret["metadata"]["name"]] = set(secret["stringData"])
    refs = [e["valueFrom"]["secretKeyRef"] for o in objects if o["kind"] in ("StatefulSet", "Deployment")
            for c in o["spec"]["template"]["spec"]["containers"] for e in c.get("env", [])
            if "secretKeyRef" in e.get("valueFrom", {})]
    assert refs and all(r["key"] in keys.get(r["name"], ()) for r in refs), refs
    sm = one(objects, "ServiceMonitor")
    cred = sm["spec"]["endpoints"][0]["authorization"]["credentials"]
    assert cred["key"] in keys.get(cred["name"], ())


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
    sts = daemon(objects)
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
    services = daemon_services(objects)
    assert "mcdenoise" in [s["metadata"]["name"] for s in services]
    for svc in services:
        assert svc["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
        for p in svc["spec"]["ports"]:
            assert p["targetPort"] in ports
    pdb = one(objects, "PodDisruptionBudget", "mcdenoise")
    assert pdb["spec"]["selector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    # The data volume is where the image keeps the job store (the scratch cache in
    # shared mode: test_scale_out_runs_the_daemon_as_a_deployment).
    mounts = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}
    assert mounts["data"] == env["MCDENOISE_DATA_DIR"]
    if sts["kind"] == "StatefulSet":
        assert sts["spec"]["serviceName"] == one(objects, "Service", "mcdenoise-headless")["metadata"]["name"]
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
    sts = daemon(objects)
    c = sts["spec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e.get("value") for e in c["env"]}
    timeout = duration_s(env.get("MCDENOISE_SHUTDOWN_TIMEOUT") or env_defaults()["MCDENOISE_SHUTDOWN_TIMEOUT"])
    # The daemon's bound (src/server.rs `run`): the shutdown timeout, WORKER_GRACE for
    # running jobs to stop at a tile, WORKER_GRACE to join the workers, TRANSPORT_GRACE.
    drain = timeout + 2 * grace["WORKER_GRACE"] + grace["TRANSPORT_GRACE"]
    assert sts["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] > drain


def test_env_vars_are_options_of_the_daemon(objects):
    known = known_env_vars()
    c = daemon(objects)["spec"]["template"]["spec"]["containers"][0]
    names = [e["name"] for e in c["env"]]
    assert set(names) <= known, set(names) - known
    assert len(names) == len(set(names))
    for e in c["env"]:
        if e["name"] in ("MCDENOISE_SHUTDOWN_TIMEOUT", "MCDENOISE_RESULT_TTL", "MCDENOISE_NATS_ACK_WAIT"):
            duration_s(e["value"])
    assert c["resources"]["requests"]["cpu"] and c["resources"]["requests"]["memory"]
    assert "memory" in c["resources"]["limits"]


def test_overlays_size_workers_to_the_cpu_request():
    for o in ["overlays/cpu", "overlays/gpu", SCALE_OUT]:
        c = daemon(render(o))["spec"]["template"]["spec"]["containers"][0]
        env = {e["name"]: e.get("value") for e in c["env"]}
        threads = int(env["MCDENOISE_WORKERS"]) * int(env["MCDENOISE_THREADS_PER_WORKER"])
        assert threads == int(c["resources"]["requests"]["cpu"]), o
        assert one(render(o), "Service", "mcdenoise")["metadata"]["namespace"] == "mcdenoise"


def test_only_the_gpu_overlay_runs_the_gpu_image_on_a_gpu():
    """overlays/gpu: the image built with `--target gpu` (its tag ends in -gpu), one
    nvidia.com/gpu per pod, `--device cuda`; every other overlay: the CPU image, no GPU."""
    for o in KUSTOMIZATIONS:
        c = daemon(render(o))["spec"]["template"]["spec"]["containers"][0]
        env = {n: e.get("value") for n, e in env_of(c).items()}
        limits = c["resources"].get("limits", {})
        if o == "overlays/gpu":
            assert c["image"].endswith("-gpu"), c["image"]
            assert str(limits.get("nvidia.com/gpu")) == "1" and env.get("MCDENOISE_DEVICE") == "cuda"
        else:
            assert not c["image"].endswith("-gpu") and "nvidia.com/gpu" not in limits, o
            assert env.get("MCDENOISE_DEVICE", "cpu") == "cpu", o


def test_hpa_scales_the_daemon_on_the_adapter_metric(objects):
    hpa = one(objects, "HorizontalPodAutoscaler")
    workload = daemon(objects)
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": workload["kind"], "name": workload["metadata"]["name"]}
    (metric,) = hpa["spec"]["metrics"]
    config = yaml.safe_load(ADAPTER_RULES.read_text())
    rules, external = config["rules"], config["externalRules"]
    if workload["kind"] == "StatefulSet":
        # One store per pod: the per-pod queue, averaged over the pods.
        assert metric["type"] == "Pods" and metric["pods"]["metric"]["name"] in {r["name"]["as"] for r in rules}
    else:
        # One shared queue, reported alike by every replica: External, divided by the
        # replica count (AverageValue), never a Pods average.
        assert metric["type"] == "External" and metric["external"]["target"]["type"] == "AverageValue"
        assert metric["external"]["metric"]["name"] in {r["name"]["as"] for r in external}
    for r in rules:
        assert set(r["resources"]["overrides"]) == {"namespace", "pod"}
        assert "<<.LabelMatchers>>" in r["metricsQuery"] and "<<.GroupBy>>" in r["metricsQuery"]
    for r in external:
        # Namespaced by the HPA's namespace; max, not sum, over the replicas' equal series.
        assert set(r["resources"]["overrides"]) == {"namespace"}
        assert "<<.LabelMatchers>>" in r["metricsQuery"]
        assert r["metricsQuery"].startswith("max(") and "sum" not in r["metricsQuery"]


# --- scale-out: shared mode on NATS JetStream ---------------------------------------


def nats_statefulset(objs):
    return one(objs, "StatefulSet", "nats")


def nats_conf(objs) -> str:
    sts = nats_statefulset(objs)
    (vol,) = [v for v in sts["spec"]["template"]["spec"]["volumes"] if "configMap" in v]
    return one(objs, "ConfigMap", vol["configMap"]["name"])["data"]["nats.conf"]


def test_the_other_overlays_render_no_shared_mode():
    for o in ["base", "overlays/cpu", "overlays/gpu"]:
        objs = render(o)
        assert daemon(objs)["kind"] == "StatefulSet"
        env = env_of(daemon(objs)["spec"]["template"]["spec"]["containers"][0])
        assert not {n for n in env if n == "MCDENOISE_STORE" or n.startswith("MCDENOISE_NATS_")}
        assert not [x for x in objs if x["metadata"]["name"].startswith("nats")]


def test_scale_out_runs_the_daemon_as_a_deployment(scale_out):
    dep = daemon(scale_out)
    assert dep["kind"] == "Deployment" and dep["spec"]["replicas"] == 2
    assert not [o for o in scale_out if o["kind"] == "StatefulSet" and o["metadata"]["name"] == "mcdenoise"]
    assert "volumeClaimTemplates" not in dep["spec"] and "serviceName" not in dep["spec"]
    # The base's pod template, unchanged where shared mode does not touch it.
    base_pod = daemon(render("overlays/cpu"))["spec"]["template"]
    pod = dep["spec"]["template"]
    assert pod["metadata"]["labels"] == base_pod["metadata"]["labels"]
    assert dep["spec"]["selector"] == daemon(render("overlays/cpu"))["spec"]["selector"]
    for key in ("securityContext", "terminationGracePeriodSeconds"):
        assert pod["spec"][key] == base_pod["spec"][key]
    c, base_c = pod["spec"]["containers"][0], base_pod["spec"]["containers"][0]
    for key in ("image", "args", "ports", "startupProbe", "livenessProbe", "readinessProbe", "resources", "securityContext", "volumeMounts"):
        assert c[key] == base_c[key], key
    # The data directory is a scratch emptyDir, nothing else of the pod changed.
    volumes = {v["name"]: v for v in pod["spec"]["volumes"]}
    assert set(volumes) == {"data", "tmp"} and "emptyDir" in volumes["data"]
    assert {m["name"]: m["mountPath"] for m in c["volumeMounts"]}["data"] == env_defaults()["MCDENOISE_DATA_DIR"]
    # Shared mode: the store URL (credentials) only from the Secret, never a plain value.
    env, base_env = env_of(c), env_of(base_c)
    assert set(env) - set(base_env) == {"MCDENOISE_STORE", "MCDENOISE_NATS_REPLICAS", "MCDENOISE_NATS_ACK_WAIT"}
    assert all(env[n] == base_env[n] for n in base_env)
    assert set(env["MCDENOISE_STORE"]) == {"name", "valueFrom"}
    assert env["MCDENOISE_STORE"]["valueFrom"]["secretKeyRef"] == {"name": "mcdenoise-nats", "key": "url"}
    # As many copies of the data as NATS servers.
    assert env["MCDENOISE_NATS_REPLICAS"]["value"] == "3" == str(nats_statefulset(scale_out)["spec"]["replicas"])
    assert duration_s(env["MCDENOISE_NATS_ACK_WAIT"]["value"]) >= 10
    assert set(shared_mode_docs()["env"]) >= {"MCDENOISE_STORE", "MCDENOISE_NATS_REPLICAS", "MCDENOISE_NATS_ACK_WAIT", "MCDENOISE_NATS_PREFIX"}
    # Any replica answers for any job: no affinity, no per-pod Service.
    assert [s["metadata"]["name"] for s in daemon_services(scale_out)] == ["mcdenoise"]
    svc = one(scale_out, "Service", "mcdenoise")
    assert svc["spec"].get("sessionAffinity", "None") == "None" and "sessionAffinityConfig" not in svc["spec"]
    assert one(scale_out, "Service", "mcdenoise")["metadata"]["namespace"] == "mcdenoise"


def test_scale_out_nats_cluster(scale_out):
    sts = nats_statefulset(scale_out)
    spec, pod = sts["spec"], sts["spec"]["template"]["spec"]
    assert spec["replicas"] == 3 and spec["podManagementPolicy"] == "Parallel"
    assert spec["selector"]["matchLabels"].items() <= sts["spec"]["template"]["metadata"]["labels"].items()
    (c,) = pod["containers"]
    assert re.fullmatch(r"nats:2\.10\.\d+(-alpine)?", c["image"]), c["image"]
    ports = {p["name"]: p["containerPort"] for p in c["ports"]}
    assert ports == {"nats": 4222, "cluster": 6222, "monitor": 8222}
    # Services: clients on 4222 (ready servers), the governing headless one for the routes.
    headless = one(scale_out, "Service", spec["serviceName"])
    assert headless["spec"]["clusterIP"] == "None" and headless["spec"]["publishNotReadyAddresses"]
    client = one(scale_out, "Service", "nats")
    assert [(p["port"], p["targetPort"]) for p in client["spec"]["ports"]] == [(4222, "nats")]
    for svc in (headless, client):
        assert svc["spec"]["selector"].items() <= sts["spec"]["template"]["metadata"]["labels"].items()
        assert all(p["targetPort"] in ports for p in svc["spec"]["ports"])
    # The daemon's Service and ServiceMonitor do not pick up the NATS pods.
    sm = one(scale_out, "ServiceMonitor")["spec"]["selector"]["matchLabels"]
    assert not sm.items() <= headless["metadata"]["labels"].items()
    assert not one(scale_out, "Service", "mcdenoise")["spec"]["selector"].items() <= sts["spec"]["template"]["metadata"]["labels"].items()
    pdb = one(scale_out, "PodDisruptionBudget", "nats")
    assert pdb["spec"] == {"maxUnavailable": 1, "selector": {"matchLabels": spec["selector"]["matchLabels"]}}
    # Probes on the monitoring port.
    for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
        assert c[probe]["httpGet"]["port"] == "monitor" and c[probe]["httpGet"]["path"].startswith("/healthz")
    # nats.conf: server names from the pods, routes to every server through the headless
    # Service, JetStream on the volume, monitoring on the probes' port.
    conf = nats_conf(scale_out)
    env = env_of(c)
    assert re.search(r"^server_name: \$POD_NAME$", conf, re.M)
    assert env["POD_NAME"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert re.search(rf"^port: {ports['nats']}$", conf, re.M) and re.search(rf"^http_port: {ports['monitor']}$", conf, re.M)
    cluster = re.search(r"^cluster \{(.*?)^\}", conf, re.M | re.S).group(1)
    assert re.search(rf"^\s*port: {ports['cluster']}$", cluster, re.M)
    routes = re.findall(r"nats://(\S+)", cluster)
    assert routes == [f"{sts['metadata']['name']}-{i}.{headless['metadata']['name']}:{ports['cluster']}" for i in range(spec["replicas"])]
    jetstream = re.search(r"^jetstream \{(.*?)^\}", conf, re.M | re.S).group(1)
    store_dir = re.search(r"^\s*store_dir: (\S+)$", jetstream, re.M).group(1)
    mounts = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}
    assert [t["metadata"]["name"] for t in spec["volumeClaimTemplates"]] == ["data"] and mounts["data"] == store_dir
    pvc_gib = int(spec["volumeClaimTemplates"][0]["spec"]["resources"]["requests"]["storage"].removesuffix("Gi"))
    max_file = int(re.search(r"^\s*max_file_store: (\d+)Gi$", jetstream, re.M).group(1))
    assert max_file < pvc_gib
    # The pid file of the lame-duck preStop hook is on a writable volume.
    pid_file = re.search(r"^pid_file: (\S+)$", conf, re.M).group(1)
    assert os.path.dirname(pid_file) in mounts.values()
    assert c["lifecycle"]["preStop"]["exec"]["command"] == ["nats-server", "--signal", f"ldm={pid_file}"]
    assert int(re.search(r"^lame_duck_duration: (\d+)s$", conf, re.M).group(1)) < pod["terminationGracePeriodSeconds"]
    # The user's password from the Secret whose other key is the daemon's URL.
    assert re.search(r"^\s*password: \$NATS_PASSWORD$", conf, re.M)
    assert env["NATS_PASSWORD"]["valueFrom"]["secretKeyRef"] == {"name": "mcdenoise-nats", "key": "password"}
    assert pod["securityContext"]["runAsNonRoot"] and c["securityContext"]["readOnlyRootFilesystem"]


def test_scale_out_network_policy_admits_the_daemon_and_the_peers(scale_out):
    pol = one(scale_out, "NetworkPolicy", "nats")["spec"]
    nats_labels = nats_statefulset(scale_out)["spec"]["template"]["metadata"]["labels"]
    daemon_labels = daemon(scale_out)["spec"]["template"]["metadata"]["labels"]
    assert pol["podSelector"]["matchLabels"].items() <= nats_labels.items()
    by_port = {r["ports"][0]["port"]: r.get("from") for r in pol["ingress"]}
    assert by_port.keys() == {"nats", "cluster", "monitor"}
    assert [f["podSelector"]["matchLabels"].items() <= daemon_labels.items() for f in by_port["nats"]] == [True]
    assert [f["podSelector"]["matchLabels"].items() <= nats_labels.items() for f in by_port["cluster"]] == [True]
    assert by_port["monitor"] is None  # the probes


def test_nats_server_accepts_the_configuration(scale_out, tmp_path):
    server = shutil.which("nats-server")
    if not server:
        pytest.skip("nats-server is not installed")
    conf = tmp_path / "nats.conf"
    conf.write_text(nats_conf(scale_out))
    env = dict(os.environ, POD_NAME="nats-0", NATS_PASSWORD="nats0123456789abcdef")
    r = subprocess.run([server, "-t", "-c", str(conf)], capture_output=True, text=True, env=env, timeout=30)
    assert r.returncode == 0 and "is valid" in r.stdout + r.stderr, r.stdout + r.stderr
    # The variables it reads are the container's.
    names = set(re.findall(r"\$([A-Z_]+)", nats_conf(scale_out)))
    assert names <= set(env_of(nats_statefulset(scale_out)["spec"]["template"]["spec"]["containers"][0]))
    env.pop("NATS_PASSWORD")
    assert subprocess.run([server, "-t", "-c", str(conf)], capture_output=True, env=env, timeout=30).returncode != 0


def test_nats_container_refuses_a_weak_password(scale_out, tmp_path):
    c = nats_statefulset(scale_out)["spec"]["template"]["spec"]["containers"][0]
    assert c["command"] == ["/bin/sh", "-ec"]
    (script,) = c["args"]
    mount = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}["config"]
    assert f"exec nats-server --config {mount}/nats.conf" in script
    # A stand-in nats-server that reports its arguments.
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "nats-server").write_text('#!/bin/sh\necho "started $*"\n')
    (fake / "nats-server").chmod(0o755)

    def start(password):
        env = {"PATH": f"{fake}:/usr/bin:/bin", "NATS_PASSWORD": password}
        return subprocess.run(["/bin/sh", "-ec", script], capture_output=True, text=True, env=env, timeout=10)

    for bad in ["", "short1", "0123456789abcdef0123", "nats0123456789abc-ef", "nats0123456789abcd f", "nats0123456789abcd$"]:
        r = start(bad)
        assert r.returncode == 1 and "mcdenoise-nats" in r.stderr and "started" not in r.stdout, bad
    good = start("nats" + "0123456789abcdef" * 3)
    assert good.returncode == 0 and good.stdout.strip() == f"started --config {mount}/nats.conf", good.stderr


def test_scale_out_hpa_reads_a_documented_metric(scale_out):
    hpa = one(scale_out, "HorizontalPodAutoscaler")
    (metric,) = hpa["spec"]["metrics"]
    name = metric["external"]["metric"]["name"]
    assert name == "mcdenoise_shared_queue_messages"
    # The adapter's external rule serves exactly this series under this name.
    (rule,) = [r for r in yaml.safe_load(ADAPTER_RULES.read_text())["externalRules"] if r["name"]["as"] == name]
    assert rule["seriesQuery"].startswith(name + "{") and re.fullmatch(rf"\^{name}\$", rule["name"]["matches"])
    assert rule["metricsQuery"] == f"max({name}{{<<.LabelMatchers>>}})"
    # A metric the daemon documents for shared mode, with the rule as the doc shows it.
    assert name in shared_mode_docs()["metrics"]
    section = DEPLOY_DOC.read_text().split("\n## Scale-out")[1].split("\n## ")[0]
    (snippet,) = [b for b in re.findall(r"```yaml\n(.*?)```", section, re.S) if "externalRules:" in b]
    assert yaml.safe_load(snippet)["externalRules"] == yaml.safe_load(ADAPTER_RULES.read_text())["externalRules"]
    assert hpa["spec"]["minReplicas"] == daemon(scale_out)["spec"]["replicas"] <= hpa["spec"]["maxReplicas"]
