"""deploy/kuberay/raycluster.yaml matches deploy/k8s/esa.yaml (structure only: no cluster here).

The RayCluster's pods must name the esa-server shards that esa.yaml defines (Service, port,
number of shards), mount the token Secret its servers read, and build a valid EsaService.
"""

import re
from pathlib import Path

import pytest
import yaml

from esa_client.rllib.service import EsaService

ROOT = Path(__file__).resolve().parents[2]
RAYCLUSTER = ROOT / "deploy" / "kuberay" / "raycluster.yaml"
ESA = ROOT / "deploy" / "k8s" / "esa.yaml"
CONTAINERFILE = ROOT / "deploy" / "kuberay" / "Containerfile"


@pytest.fixture(scope="module")
def cluster():
    return yaml.safe_load(RAYCLUSTER.read_text())


@pytest.fixture(scope="module")
def esa():
    docs = {doc["kind"]: doc for doc in yaml.safe_load_all(ESA.read_text())}
    assert set(docs) == {"Service", "StatefulSet"}
    return docs


def pods(cluster):
    head = cluster["spec"]["headGroupSpec"]["template"]["spec"]
    return [("head", head)] + [
        (group["groupName"], group["template"]["spec"])
        for group in cluster["spec"]["workerGroupSpecs"]
    ]


def env_of(container):
    return {var["name"]: var for var in container["env"]}


def server_container(esa):
    (container,) = esa["StatefulSet"]["spec"]["template"]["spec"]["containers"]
    return container


def server_flag(container, flag):
    (value,) = [arg.split("=", 1)[1] for arg in container["args"] if arg.startswith(flag + "=")]
    return value


def test_the_service_runs_esa_server_with_its_state_file(esa):
    service, statefulset = esa["Service"], esa["StatefulSet"]
    assert statefulset["spec"]["serviceName"] == service["metadata"]["name"]
    labels = statefulset["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["selector"].items() <= labels.items()
    container = server_container(esa)
    assert container["image"].split("/")[-1].startswith("esa-server:")
    state_file = server_flag(container, "--state-file")
    (mount,) = [m for m in container["volumeMounts"] if state_file.startswith(m["mountPath"] + "/")]
    claims = [claim["metadata"]["name"] for claim in statefulset["spec"]["volumeClaimTemplates"]]
    assert mount["name"] in claims  # a volume per shard, kept across restarts


def test_kuberay_structure(cluster):
    assert cluster["apiVersion"] == "ray.io/v1"
    assert cluster["kind"] == "RayCluster"
    spec = cluster["spec"]
    head = spec["headGroupSpec"]
    assert head["rayStartParams"]["num-cpus"] == "0"  # env runners go to the workers
    assert isinstance(head["template"]["spec"]["containers"], list)
    assert spec["workerGroupSpecs"]
    for group in spec["workerGroupSpecs"]:
        assert group["groupName"]
        assert isinstance(group["rayStartParams"], dict)
        assert group["minReplicas"] <= group["replicas"] <= group["maxReplicas"]
    for _, pod in pods(cluster):
        for container in pod["containers"]:
            resources = container["resources"]
            assert resources["requests"] == resources["limits"]  # Ray counts the limits


def test_ray_version_is_the_images(cluster):
    (base,) = re.findall(r"^ARG RAY_IMAGE=rayproject/ray:(\S+)$", CONTAINERFILE.read_text(), re.M)
    assert base.split("-")[0] == cluster["spec"]["rayVersion"]
    assert "[rllib,zenoh]" in CONTAINERFILE.read_text()


def test_every_pod_reaches_the_shards_with_the_token(cluster, esa):
    service = esa["Service"]
    name = service["metadata"]["name"]
    (zenoh_port,) = [p["port"] for p in service["spec"]["ports"] if p["name"] == "zenoh"]
    server = server_container(esa)
    shards = esa["StatefulSet"]["spec"]["replicas"]
    assert env_of(server)["ESA_SHARDS"]["value"] == str(shards)
    assert f"--zenoh-listen=tcp/0.0.0.0:{zenoh_port}" in server["args"]
    server_token = server_flag(server, "--auth-token-file")
    (server_secret,) = [
        v["secret"]
        for v in esa["StatefulSet"]["spec"]["template"]["spec"]["volumes"]
        if "secret" in v
    ]
    expected = ",".join(
        f"tcp/{name}-{i}.{name}.$(POD_NAMESPACE).svc:{zenoh_port}" for i in range(shards)
    )
    for group, pod in pods(cluster):
        (container,) = pod["containers"]
        env = env_of(container)
        names = [var["name"] for var in container["env"]]
        # $(POD_NAMESPACE) expands only when defined before its use.
        assert names.index("POD_NAMESPACE") < names.index("ESA_ZENOH"), group
        assert env["POD_NAMESPACE"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.namespace"
        assert env["ESA_ZENOH"]["value"] == expected, group
        assert env["ESA_SHARDS"]["value"] == str(shards), group
        token_file = env["ESA_TOKEN_FILE"]["value"]
        assert Path(token_file).name == Path(server_token).name
        (mount,) = [
            m for m in container["volumeMounts"] if token_file.startswith(m["mountPath"] + "/")
        ]
        assert mount["readOnly"] is True
        (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
        assert volume["secret"] == server_secret, group  # esa-token, key token


def test_the_env_builds_the_sharded_service(cluster):
    (container,) = cluster["spec"]["headGroupSpec"]["template"]["spec"]["containers"]
    env = {
        name: var["value"].replace("$(POD_NAMESPACE)", "ns")
        for name, var in env_of(container).items()
        if "value" in var
    }
    service = EsaService(
        zenoh=env["ESA_ZENOH"].split(","),
        shards=int(env["ESA_SHARDS"]),
        token_file=env["ESA_TOKEN_FILE"],
    )
    assert not service.in_process
    assert service.zenoh == ("tcp/esa-0.esa.ns.svc:7447", "tcp/esa-1.esa.ns.svc:7447")
