"""launch/kubernetes/: each JobSet manifest, filled in with the example parameters of its header,
is a valid JobSet (the JobSet CRD's schema, vendored in launch/kubernetes/schema/) whose jobs are
valid batch/v1 Jobs (kubernetes-validate's schemas, unknown fields refused), and its pods run
train.py with the config and the workdir, JAX's coordinator being pod 0 behind the headless
service."""

import json
import math
import pathlib
import re
import shlex
import string

import jsonschema
import kubernetes_validate
import pytest
import yaml

REPO = pathlib.Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "kubernetes"
MANIFESTS = sorted(LAUNCH.glob("jobset-*.yaml"))
KUBERNETES_VERSION = "1.31.0"


def _example_parameters(text: str) -> dict:
  """The `export NAME=VALUE ...` lines of the manifest's header comment."""
  header = "\n".join(l[1:].strip() for l in text.splitlines() if l.startswith("#"))
  m = re.search(r"export (.*?)\n\s*envsubst", header, re.S)
  assert m, "the header shows no `export ... envsubst` example"
  words = shlex.split(m.group(1).replace("\\\n", " "))
  return dict(w.split("=", 1) for w in words)


def _strict(schema):
  """The schema with unknown fields refused, as the API server's strict field validation does
  (a CRD's schema lists the known fields but allows others)."""
  if isinstance(schema, list):
    return [_strict(s) for s in schema]
  if not isinstance(schema, dict):
    return schema
  out = {k: _strict(v) for k, v in schema.items()}
  if ("properties" in out and "additionalProperties" not in out
      and not out.get("x-kubernetes-preserve-unknown-fields")
      and not out.get("x-kubernetes-embedded-resource")):
    out["additionalProperties"] = False
  return out


def _render(path):
  text = path.read_text()
  params = _example_parameters(text)
  placeholders = set(re.findall(r"\$\{(\w+)\}", "\n".join(
      l for l in text.splitlines() if not l.startswith("#"))))
  assert placeholders <= set(params), f"{path.name}: no example for {placeholders - set(params)}"
  return yaml.safe_load(string.Template(text).substitute(params)), params


def test_manifests_exist():
  assert {p.name for p in MANIFESTS} == {"jobset-tpu.yaml", "jobset-gpu.yaml"}


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_jobset_is_valid_and_runs_train_py(path):
  jobset, params = _render(path)
  schema = json.loads((LAUNCH / "schema" / "jobset.x-k8s.io_v1alpha2.json").read_text())
  jsonschema.validate(jobset, _strict(schema))
  assert jobset["apiVersion"] == "jobset.x-k8s.io/v1alpha2" and jobset["kind"] == "JobSet"
  assert jobset["spec"]["network"]["enableDNSHostnames"] is True
  subdomain = jobset["spec"]["network"].get("subdomain", jobset["metadata"]["name"])

  (rjob,) = jobset["spec"]["replicatedJobs"]
  job = {"apiVersion": "batch/v1", "kind": "Job", "metadata": {"name": rjob["name"]},
         "spec": rjob["template"]["spec"]}
  kubernetes_validate.validate(job, KUBERNETES_VERSION, strict=True)
  spec = job["spec"]
  hosts = int(params["HOSTS"])
  assert spec["completionMode"] == "Indexed"
  assert spec["parallelism"] == spec["completions"] == hosts

  pod = spec["template"]["spec"]
  (container,) = pod["containers"]
  argv = container["command"] + container.get("args", [])
  assert argv[:2] == ["python", "train.py"]
  assert f"--config={params['CONFIG']}" in argv
  assert any(a.startswith("--workdir=/runs/") for a in argv)
  mounts = {m["mountPath"]: m["name"] for m in container["volumeMounts"]}
  claims = {v["name"]: v["persistentVolumeClaim"]["claimName"] for v in pod["volumes"]
            if "persistentVolumeClaim" in v}
  assert claims[mounts["/runs"]] == params["RUNS_CLAIM"]   # the workdir is on the shared volume

  env = {e["name"]: e for e in container["env"]}
  coordinator = env["JAX_COORDINATOR_ADDRESS"]["value"]
  # JobSet's pod DNS name: <jobset>-<replicated job>-<job index>-<pod index>.<subdomain>
  assert coordinator.startswith(f"{jobset['metadata']['name']}-{rjob['name']}-0-0.{subdomain}:")
  assert env["JAX_NUM_PROCESSES"]["value"] == str(hosts)
  assert "job-completion-index" in env["JAX_PROCESS_ID"]["valueFrom"]["fieldRef"]["fieldPath"]
  assert pod["terminationGracePeriodSeconds"] >= 60   # time for the SIGTERM save
  limits = container["resources"]["limits"]
  assert ("google.com/tpu" in limits) == ("tpu" in path.name)
  assert ("nvidia.com/gpu" in limits) == ("gpu" in path.name)


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_the_plans_overrides_reach_train_py(path):
  """MESH, GLOBAL_BATCH and GRAD_ACCUM (what `benchmarks/train_step.py --fit` prints) arrive as
  train.py's --config overrides, and the example's values make a run train.py accepts on the
  example's chips: the mesh covers them, the batch splits into the microbatches on every chip."""
  from ufm_jax.training import accumulation, config_lib, sharding
  jobset, params = _render(path)
  (container,) = jobset["spec"]["replicatedJobs"][0]["template"]["spec"]["template"]["spec"][
      "containers"]
  argv = container["command"] + container.get("args", [])
  assert f"--config.mesh={params['MESH']}" in argv
  assert f"--config.input.batch_size={params['GLOBAL_BATCH']}" in argv
  assert f"--config.grad_accum={params['GRAD_ACCUM']}" in argv
  per_host = int(params.get("CHIPS_PER_HOST") or params["GPUS_PER_HOST"])
  chips = int(params["HOSTS"]) * per_host
  if "TPU_TOPOLOGY" in params:
    assert chips == math.prod(int(d) for d in params["TPU_TOPOLOGY"].split("x"))
  sizes = dict(sharding.parse_mesh(params["MESH"]))
  known = math.prod(s for s in sizes.values() if s != -1)
  assert chips % known == 0 and (-1 in sizes.values() or known == chips)
  config = config_lib.load_config(str(REPO / params["CONFIG"]))   # PATH:ARG, as train.py reads it
  batch, k = int(params["GLOBAL_BATCH"]), int(params["GRAD_ACCUM"])
  assert batch % chips == 0
  accumulation.check_divisible(batch, k, chips, accumulation.pair_rows(config.apply_kwargs))


def test_validation_refuses_a_misspelt_field():
  jobset, _ = _render(LAUNCH / "jobset-gpu.yaml")
  bad = json.loads(json.dumps(jobset))
  bad["spec"]["network"]["enableDNSHostname"] = True
  schema = json.loads((LAUNCH / "schema" / "jobset.x-k8s.io_v1alpha2.json").read_text())
  with pytest.raises(jsonschema.ValidationError, match="enableDNSHostname"):
    jsonschema.validate(bad, _strict(schema))
  spec = jobset["spec"]["replicatedJobs"][0]["template"]["spec"]
  spec["template"]["spec"]["containers"][0]["comand"] = ["python"]
  with pytest.raises(kubernetes_validate.ValidationError, match="comand"):
    kubernetes_validate.validate({"apiVersion": "batch/v1", "kind": "Job",
                                  "metadata": {"name": "w"}, "spec": spec},
                                 KUBERNETES_VERSION, strict=True)
