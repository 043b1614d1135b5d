#!/usr/bin/env bash
# Validates deploy/k8s against the Kubernetes schemas, offline (the PyPI package
# kubernetes-validate ships them), strictly: an unknown field is an error. Then checks that the
# check can fail: a copy of the Deployment with a misspelt field must be refused.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/ci-tools
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
[ -x "$venv/bin/kubernetes-validate" ] || "$venv/bin/pip" install -q kubernetes-validate==1.37.0
"$venv/bin/kubernetes-validate" --strict --quiet deploy/k8s/*.yaml deploy/k8s/encode/*.yaml
broken=$(mktemp -d)
trap 'rm -rf "$broken"' EXIT
sed 's/readinessProbe:/readinesProbe:/' deploy/k8s/deployment.yaml > "$broken/deployment.yaml"
if "$venv/bin/kubernetes-validate" --strict --quiet "$broken/deployment.yaml" >/dev/null 2>&1; then
  echo "k8s: a misspelt field passed validation" >&2
  exit 1
fi
echo "k8s: deploy/k8s validates (and a broken copy does not)"
