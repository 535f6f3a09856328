"""Deployment files (issue 6): image, compose, Helm values, DaskCluster, TLS certificates, preload.

No Docker engine or Kubernetes runs here, so nothing is built or applied. What is checked:
the files parse and have the expected structure; every dask setting they pass as a
``DASK_...`` environment variable is a real key of distributed's configuration; the paths and
pins the Dockerfile refers to exist and agree with the development venv; ``deploy/make-certs.sh``
produces a CA and certificates that a real TLS scheduler, worker and client accept (and that a
client without them is refused), configured exactly as compose and the Helm values configure
them; and the preload's ``--geocoder-version`` check refuses a worker of another version.
"""

from __future__ import annotations

import ast
import asyncio
import importlib.util
import ipaddress
import os
import re
import shutil
import stat
import subprocess
import sys
import time
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from unittest import mock

import dask
import dask.config
import distributed
import pytest
import yaml
from distributed import Client, Scheduler, Security, Worker
from distributed.comm import connect

import geocoder
from geocoder.runtime import WORKER_ENV

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
WORKERS = ROOT / "workers"
PRELOAD = WORKERS / "geocoder_preload.py"
TLS_DIR = "/etc/geocoder/tls"  # where every deployment mounts the certificates
IMAGE_PRELOAD = "/opt/geocoder/geocoder_preload.py"
CERT_FILES = {f"{n}.pem" for n in ("ca", "ca-key", "scheduler", "scheduler-key", "worker", "worker-key", "client", "client-key")}
# DASK_ variables that are not nested distributed/dask settings.
SPECIAL_DASK_VARS = {"DASK_CONFIG", "DASK_SCHEDULER_ADDRESS"}


# ----------------------------------------------------------------------------- helpers


def load_yaml(path: Path):
    return yaml.safe_load(path.read_text())


def interpolate(value):
    """Compose-style ``${VAR:-default}`` / ``${VAR}`` interpolation with an empty environment."""
    if not isinstance(value, str):
        return value
    return re.sub(r"\$\{(\w+)(?::?-([^}]*))?\}", lambda m: m.group(2) or "", value)


def env_dict(env) -> dict:
    """A compose ``environment`` mapping or a Kubernetes ``env`` list as {name: value or valueFrom}."""
    if env is None:
        return {}
    if isinstance(env, dict):
        return {k: interpolate(v) for k, v in env.items()}
    return {e["name"]: e["value"] if "value" in e else e["valueFrom"] for e in env}


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{str(k).replace('_', '-')}"
        if isinstance(v, dict) and v:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _site_yaml(package, name: str) -> dict:
    return load_yaml(Path(package.__file__).parent / name)


DEFAULT_KEYS = set(_flatten(_site_yaml(dask, "dask.yaml"))) | set(_flatten(_site_yaml(distributed, "distributed.yaml")))


def _schema_has(schema: dict, dotted: str) -> bool:
    node = schema
    for part in dotted.split("."):
        props = node.get("properties", {})
        if part not in props:
            return False
        node = props[part]
    return True


SCHEMAS = [_site_yaml(dask, "dask-schema.yaml"), _site_yaml(distributed, "distributed-schema.yaml")]


def dask_settings(env: dict) -> dict:
    """The dask config the ``DASK_*`` variables of ``env`` produce, as {dotted.key: value} (dask's own parser)."""
    plain = {k: v for k, v in env.items() if k.startswith("DASK_") and k not in SPECIAL_DASK_VARS and isinstance(v, str)}
    return _flatten(dask.config.collect_env(plain))


def assert_real_dask_keys(env: dict, where: str) -> None:
    names = [k for k in env if k.startswith("DASK_") and k not in SPECIAL_DASK_VARS]
    assert names, f"{where}: no dask settings"
    for name in names:
        dotted = ".".join(part.lower().replace("_", "-") for part in name[len("DASK_"):].split("__"))
        assert dotted in DEFAULT_KEYS, f"{where}: {name} -> {dotted} is not a dask/distributed config key"
        assert any(_schema_has(s, dotted) for s in SCHEMAS), f"{where}: {dotted} not in the config schema"
    if "DASK_DISTRIBUTED__COMM__REQUIRE_ENCRYPTION" in env:
        assert dask_settings(env)["distributed.comm.require-encryption"] is True


def tls_roles(env: dict) -> set[str]:
    return {m.group(1).lower() for k in env if (m := re.fullmatch(r"DASK_DISTRIBUTED__COMM__TLS__(\w+?)__(CERT|KEY)", k))}


def resolve_env(env: dict, certs: Path) -> dict:
    """Deployment env as it reaches the process: certificate paths moved to ``certs``, secret refs read."""
    out = {}
    for k, v in env.items():
        if isinstance(v, dict):  # Kubernetes valueFrom: the secret key's content
            out[k] = (certs / v["secretKeyRef"]["key"]).read_text()
        else:
            out[k] = str(v).replace(TLS_DIR, str(certs))
    return out


def security_from_env(env: dict) -> Security:
    """The distributed.Security a process started with ``env`` builds from its dask config."""
    with dask.config.set(dask_settings(env)):
        return Security()


@contextmanager
def preserved_environ():
    """Importing the preload sets thread variables in os.environ: keep them out of this process."""
    with mock.patch.dict(os.environ):
        yield


def import_preload():
    with preserved_environ():
        spec = importlib.util.spec_from_file_location("geocoder_preload_under_test", PRELOAD)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- files


@pytest.fixture(scope="module")
def compose():
    return load_yaml(DEPLOY / "compose.yaml")


@pytest.fixture(scope="module")
def helm():
    return load_yaml(DEPLOY / "helm" / "values.yaml")


@pytest.fixture(scope="module")
def daskcluster():
    return load_yaml(DEPLOY / "kubernetes" / "daskcluster.yaml")


def dockerfile_instructions() -> list[tuple[str, str]]:
    text = (WORKERS / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def check_worker_command(cmd: list[str], where: str) -> None:
    """``... worker ADDRESS ... --preload IMAGE_PRELOAD --geocoder-version <current version>``."""
    cmd = [interpolate(str(c)) for c in cmd]
    i = cmd.index("worker")
    assert re.match(r"(tls://|\$\()", cmd[i + 1]), f"{where}: scheduler address must come first, got {cmd[i + 1]}"
    assert cmd[cmd.index("--preload") + 1] == IMAGE_PRELOAD, where
    assert cmd.index("--geocoder-version") > cmd.index("--preload"), where
    assert cmd[cmd.index("--geocoder-version") + 1] == geocoder.__version__, f"{where}: worker version pin is stale"
    assert cmd[cmd.index("--nthreads") + 1] == "1", where


def test_compose_structure(compose):
    services = compose["services"]
    assert {"certs", "scheduler", "worker", "notebook"} <= set(services)
    for name, svc in services.items():
        assert svc["build"]["dockerfile"] == "workers/Dockerfile"
        assert (DEPLOY / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()
        assert interpolate(svc["image"]).endswith(":" + geocoder.__version__), name

    certs = services["certs"]
    script_mount = next(v for v in certs["volumes"] if v.startswith("./make-certs.sh:"))
    assert (DEPLOY / "make-certs.sh").is_file() and script_mount.split(":")[1] in " ".join(certs["entrypoint"])
    assert certs["command"] == [TLS_DIR]
    for name in ("scheduler", "worker", "notebook"):
        assert services[name]["depends_on"], name
        assert f"tls:{TLS_DIR}:ro" in services[name]["volumes"], name
    assert services["scheduler"]["depends_on"]["certs"]["condition"] == "service_completed_successfully"

    sched = services["scheduler"]
    assert sched["command"][:2] == ["dask", "scheduler"]
    assert sched["command"][sched["command"].index("--protocol") + 1] == "tls"
    assert "8786:8786" in sched["ports"] and "8787:8787" in sched["ports"]

    worker = services["worker"]
    assert "GEOCODER_WORKERS" in worker["deploy"]["replicas"]
    assert int(interpolate(worker["deploy"]["replicas"])) == 2
    check_worker_command(worker["command"], "compose worker")
    assert any(v.startswith("data:") for v in worker["volumes"])

    nb = services["notebook"]
    assert nb["command"][:2] == ["jupyter", "lab"]
    assert env_dict(nb["environment"])["DASK_SCHEDULER_ADDRESS"] == "tls://scheduler:8786"
    examples = next(v for v in nb["volumes"] if "examples" in v).split(":")[0]
    assert (DEPLOY / examples).resolve() == ROOT / "examples" and (ROOT / "examples").is_dir()


@pytest.mark.parametrize("service,role", [("scheduler", "scheduler"), ("worker", "worker"), ("notebook", "client")])
def test_compose_tls_env(compose, service, role):
    env = env_dict(compose["services"][service]["environment"])
    assert_real_dask_keys(env, f"compose {service}")
    assert tls_roles(env) == {role}
    settings = dask_settings(env)
    assert settings["distributed.comm.tls.ca-file"] == f"{TLS_DIR}/ca.pem"
    assert settings[f"distributed.comm.tls.{role}.cert"] == f"{TLS_DIR}/{role}.pem"
    assert settings[f"distributed.comm.tls.{role}.key"] == f"{TLS_DIR}/{role}-key.pem"


def _secret_keys(volumes: list[dict]) -> set[str]:
    return {item["key"] for v in volumes if "secret" in v for item in v["secret"].get("items", [])}


@pytest.mark.parametrize("section,role", [("scheduler", "scheduler"), ("worker", "worker"), ("jupyter", "client")])
def test_helm_values(helm, section, role):
    values = helm[section]
    assert values["image"]["repository"] and values["image"]["tag"] == geocoder.__version__
    env = env_dict(values["env"])
    assert_real_dask_keys(env, f"helm {section}")
    assert tls_roles(env) == {role}
    refs = {v["secretKeyRef"]["key"] for v in env.values() if isinstance(v, dict)}
    if section == "scheduler":  # the chart mounts no volumes into the scheduler: PEM text from the secret
        assert refs == {"ca.pem", "scheduler.pem", "scheduler-key.pem"}
        assert values["extraArgs"] == ["--protocol", "tls"]
    else:
        assert dask_settings(env)["distributed.comm.default-scheme"] == "tls"
        mounts = values["mounts"]
        assert _secret_keys(mounts["volumes"]) == {"ca.pem", f"{role}.pem", f"{role}-key.pem"}
        tls_mount = next(m for m in mounts["volumeMounts"] if m["mountPath"] == TLS_DIR)
        assert tls_mount["readOnly"] is True
        assert {m["name"] for m in mounts["volumeMounts"]} <= {v["name"] for v in mounts["volumes"]}
    if section == "worker":
        assert values["replicas"] >= 1 and values["threads_per_worker"] == 1
        assert values["image"]["dask_worker"] == "dask-worker"
        # the chart puts "<release>-dask-scheduler:8786" first, then extraArgs
        check_worker_command(["worker", "tls://<chart>", "--nthreads", "1", *values["extraArgs"]], "helm worker")
    assert values["securityContext"]["runAsNonRoot"] is True


def test_daskcluster(daskcluster):
    assert daskcluster["apiVersion"] == "kubernetes.dask.org/v1"
    assert daskcluster["kind"] == "DaskCluster"
    name = daskcluster["metadata"]["name"]
    spec = daskcluster["spec"]
    assert spec["worker"]["replicas"] >= 1
    for component, role in (("worker", "worker"), ("scheduler", "scheduler")):
        pod = spec[component]["spec"]
        [container] = pod["containers"]
        assert container["image"].endswith(":" + geocoder.__version__)
        assert container["args"][:2] == ["dask", component]
        env = env_dict(container["env"])
        assert_real_dask_keys(env, f"daskcluster {component}")
        assert tls_roles(env) == {role}
        assert dask_settings(env)[f"distributed.comm.tls.{role}.cert"] == f"{TLS_DIR}/{role}.pem"
        assert _secret_keys(pod["volumes"]) == {"ca.pem", f"{role}.pem", f"{role}-key.pem"}
        assert all(v["secret"]["secretName"] == "geocoder-tls" for v in pod["volumes"] if "secret" in v)
        assert any(m["mountPath"] == TLS_DIR for m in container["volumeMounts"])
        assert pod["securityContext"]["runAsNonRoot"] is True
    worker = spec["worker"]["spec"]["containers"][0]
    check_worker_command(worker["args"], "daskcluster worker")
    assert worker["args"][2] == "$(DASK_SCHEDULER_ADDRESS)"
    assert env_dict(worker["env"])["DASK_SCHEDULER_ADDRESS"] == f"tls://{name}-scheduler:8786"
    scheduler = spec["scheduler"]["spec"]["containers"][0]
    assert scheduler["args"][scheduler["args"].index("--protocol") + 1] == "tls"
    service = spec["scheduler"]["service"]
    assert service["selector"] == {"dask.org/cluster-name": name, "dask.org/component": "scheduler"}
    port_names = {p["name"]: p["port"] for p in service["ports"]}
    assert port_names == {"tcp-comm": 8786, "http-dashboard": 8787}  # the operator looks ports up by name


def test_dockerfile():
    ins = dockerfile_instructions()
    froms = [rest for op, rest in ins if op == "FROM"]
    assert froms and froms[0].split()[0] == "python:3.12-slim"
    copies = [rest.split() for op, rest in ins if op == "COPY"]
    sources = [src for args in copies for src in args[:-1] if not src.startswith("--")]
    assert set(sources) == {"pyproject.toml", "README.md", "geocoder/", "workers/"}
    assert all((ROOT / src).exists() for src in sources)
    run = " ".join(rest for op, rest in ins if op == "RUN")
    assert "pip install --no-cache-dir -r workers/requirements.txt ." in run
    assert f"workers/geocoder_preload.py {IMAGE_PRELOAD}" in run and "workers/dask.yaml /opt/geocoder/dask.yaml" in run
    assert PRELOAD.is_file() and (WORKERS / "dask.yaml").is_file()
    env = " ".join(rest for op, rest in ins if op == "ENV")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        assert f"{var}=1" in env
    assert f"MALLOC_MMAP_THRESHOLD_={WORKER_ENV['MALLOC_MMAP_THRESHOLD_']}" in env
    assert "DASK_CONFIG=/opt/geocoder/dask.yaml" in env
    users = [rest for op, rest in ins if op == "USER"]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    jl = next(rest for op, rest in ins if op == "ARG" and rest.startswith("JUPYTERLAB_VERSION="))
    assert re.fullmatch(r"JUPYTERLAB_VERSION=\d+\.\d+\.\d+", jl)
    cmd = ast.literal_eval(next(rest for op, rest in reversed(ins) if op == "CMD"))
    assert cmd[:2] == ["dask", "worker"] and cmd[cmd.index("--preload") + 1] == IMAGE_PRELOAD


def test_requirements_pinned_and_within_the_projects_bounds():
    pins = {}
    for line in (WORKERS / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            m = re.fullmatch(r"([A-Za-z0-9_.-]+)==([0-9][0-9A-Za-z.+-]*)", line)
            assert m, f"not an exact pin: {line!r}"
            pins[m.group(1).lower()] = m.group(2)
    import tomllib

    from packaging.requirements import Requirement

    deps = [Requirement(d) for d in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]]
    direct = {d.name.lower() for d in deps}
    assert direct <= set(pins), f"unpinned direct dependencies: {direct - set(pins)}"
    assert {"numcodecs", "llvmlite", "bokeh", "cryptography"} <= set(pins)
    # the image's pins must satisfy what the project asks for (a fresh `pip install` may
    # resolve newer releases than the image pins; that is the point of pinning the image)
    for d in deps:
        assert d.specifier.contains(pins[d.name.lower()], prereleases=True), f"{d.name}=={pins[d.name.lower()]} violates {d}"


# ----------------------------------------------------------------------------- certificates


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    out = tmp_path_factory.mktemp("tls") / "certs"
    env = dict(os.environ, GEOCODER_CERT_SANS="geocoder-scheduler, 10.1.2.3")
    subprocess.run(["sh", str(DEPLOY / "make-certs.sh"), str(out)], env=env, check=True, capture_output=True, timeout=60)
    return out


def test_make_certs(certs):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    assert {p.name for p in certs.iterdir()} == CERT_FILES
    load = lambda name: x509.load_pem_x509_certificate((certs / name).read_bytes())  # noqa: E731
    ca = load("ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    ca.verify_directly_issued_by(ca)
    expected_dns = {"localhost", "scheduler", "worker", "notebook", "geocoder-scheduler"}
    expected_ip = {ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("10.1.2.3")}
    for role in ("scheduler", "worker", "client"):
        cert = load(f"{role}.pem")
        cert.verify_directly_issued_by(ca)  # raises if not signed by the CA
        assert cert.issuer == ca.subject
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert set(san.get_values_for_type(x509.DNSName)) == expected_dns
        assert set(san.get_values_for_type(x509.IPAddress)) == expected_ip
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {x509.oid.ExtendedKeyUsageOID.SERVER_AUTH, x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH} <= set(eku)
        lifetime = cert.not_valid_after_utc - cert.not_valid_before_utc
        assert timedelta(days=364) <= lifetime <= timedelta(days=366)
        key = serialization.load_pem_private_key((certs / f"{role}-key.pem").read_bytes(), password=None)
        assert key.public_key().public_numbers() == cert.public_key().public_numbers()
        assert stat.S_IMODE((certs / f"{role}-key.pem").stat().st_mode) == 0o600
    # a second run keeps the existing material
    before = (certs / "ca.pem").read_bytes()
    run = subprocess.run(["sh", str(DEPLOY / "make-certs.sh"), str(certs)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and "already" in run.stdout
    assert (certs / "ca.pem").read_bytes() == before


async def refused(address: str, **kwargs) -> None:
    """Connect an asynchronous client (expected to raise), closing it whatever happens."""
    client = Client(address, asynchronous=True, timeout=3, **kwargs)
    try:
        await asyncio.wait_for(client, 20)
    finally:
        await client.close()


def test_helm_configured_tls_cluster(certs, helm):
    """Scheduler, worker and client configured by the Helm values' env (scheduler: PEM text from the secret)."""
    sec = {section: security_from_env(resolve_env(env_dict(helm[section]["env"]), certs))
           for section in ("scheduler", "worker", "jupyter")}
    assert "BEGIN CERTIFICATE" in sec["scheduler"].tls_scheduler_cert  # in-memory PEM, as in the chart
    assert all(s.require_encryption for s in sec.values())

    async def run():
        with dask.config.set({"distributed.comm.timeouts.connect": "3s"}):
            async with Scheduler(protocol="tls", port=0, dashboard_address=":0", security=sec["scheduler"]) as s:
                assert s.address.startswith("tls://")
                async with Worker(s.address, nthreads=1, security=sec["worker"]):
                    async with Client(s.address, security=sec["jupyter"], asynchronous=True) as c:
                        assert await c.submit(sum, [1, 1]) == 2
                        assert len(s.workers) == 1
                    with pytest.raises(TypeError, match="TLS"):  # no certificates: no TLS context at all
                        await refused(s.address)
                    with pytest.raises(OSError, match="(?i)certificate"):  # valid TLS, certificate from another CA
                        await refused(s.address, security=Security.temporary())

    asyncio.run(run())  # a refused client must fail, not hang: pytest-timeout and the 3 s connect timeout bound it


def _subprocess_env(service_env: dict, certs: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    env.update(resolve_env(service_env, certs))
    env["DASK_CONFIG"] = str(WORKERS / "dask.yaml")
    return env


def test_compose_configured_cli_cluster(certs, compose, tmp_path):
    """Real ``dask scheduler`` / ``dask worker --preload`` processes with the compose commands and env."""
    services = compose["services"]
    bindir = Path(sys.executable).parent
    sched_file = tmp_path / "scheduler.json"
    sched_cmd = [c for c in services["scheduler"]["command"]]
    sched_cmd[sched_cmd.index("--port") + 1] = "0"
    sched_cmd[sched_cmd.index("--dashboard-address") + 1] = ":0"
    procs = [subprocess.Popen([bindir / "dask", *sched_cmd[1:], "--host", "127.0.0.1", "--scheduler-file", sched_file],
                              env=_subprocess_env(env_dict(services["scheduler"]["environment"]), certs),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(300):
            if sched_file.exists() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        import json

        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tls://127.0.0.1:")
        worker_cmd = [interpolate(c).replace("tls://scheduler:8786", address).replace(IMAGE_PRELOAD, str(PRELOAD))
                      for c in services["worker"]["command"]]
        worker_env = _subprocess_env(env_dict(services["worker"]["environment"]), certs)
        procs.append(subprocess.Popen([bindir / "dask", *worker_cmd[1:]], env=worker_env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        nb_env = resolve_env(env_dict(services["notebook"]["environment"]), certs)
        with dask.config.set(dask_settings(nb_env)):
            with pytest.raises((OSError, TimeoutError)):  # plain TCP is not served
                asyncio.run(connect(address.replace("tls://", "tcp://"), timeout=3))
            with Client(address, timeout=30) as c:
                c.wait_for_workers(1, timeout=60)
                assert c.submit(sum, [41, 1]).result(timeout=30) == 42
                [worker_environ] = c.run(lambda: dict(os.environ)).values()
                assert worker_environ["NUMBA_NUM_THREADS"] == "1"

        # the same worker command with another version pin refuses to start
        bad = list(worker_cmd)
        bad[bad.index("--geocoder-version") + 1] = "0.0.0-bad"
        run = subprocess.run([bindir / "dask", *bad[1:]], env=worker_env, capture_output=True, text=True, timeout=60)
        assert run.returncode != 0
        assert "0.0.0-bad" in run.stderr and geocoder.__version__ in run.stderr and "version mismatch" in run.stderr
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=30)


# ----------------------------------------------------------------------------- preload version check


def test_check_version():
    preload = import_preload()
    preload.check_version(geocoder.__version__)
    preload.check_version(f" {geocoder.__version__}\n")
    with pytest.raises(RuntimeError, match=rf"expected geocoder 0\.0\.0-bad .* geocoder {re.escape(geocoder.__version__)}"):
        preload.check_version("0.0.0-bad")


def test_preload_version_option_is_a_click_command():
    import click

    preload = import_preload()
    assert isinstance(preload.dask_setup, click.Command)
    ctx = click.Context(preload.dask_setup)  # as distributed validates `dask worker` arguments
    with pytest.raises(click.BadParameter, match="0.0.0-bad"):
        preload.dask_setup.parse_args(ctx, ["--geocoder-version", "0.0.0-bad"])
    ctx = click.Context(preload.dask_setup)
    preload.dask_setup.parse_args(ctx, ["--geocoder-version", geocoder.__version__])
    assert ctx.params["geocoder_version"] == geocoder.__version__


def test_preload_refuses_programmatic_worker():
    """Worker(preload_argv=...) bypasses the command line: the worker's start must fail anyway."""

    async def run():
        async with Scheduler(port=0, dashboard_address=":0") as s:
            with pytest.raises(RuntimeError, match="failed to start") as err:
                await Worker(s.address, nthreads=1, preload=[str(PRELOAD)], preload_argv=["--geocoder-version", "0.0.0-bad"])
            assert "0.0.0-bad" in str(err.value.__cause__)
            assert not s.workers

    with preserved_environ():
        asyncio.run(run())
