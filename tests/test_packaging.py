"""The pip package and the conda environment list the same dependencies."""
import re
import tomllib

import yaml

from conftest import REPO


def _name(req: str) -> str:
    return re.split(r"[<>=!~ \[;]", req.strip(), maxsplit=1)[0].lower().replace("_", "-")


def test_conda_env_matches_pyproject():
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    pip_names = {_name(r) for r in pyproject["project"]["dependencies"]}
    env = yaml.safe_load((REPO / "envs" / "stex.yaml").read_text())
    conda_names = set()
    for dep in env["dependencies"]:
        if isinstance(dep, dict):
            conda_names |= {_name(r) for r in dep["pip"] if not r.startswith("-e")}
        elif _name(dep) not in ("python", "pip"):
            conda_names.add(_name(dep))
    assert pip_names == conda_names


def test_python_requirement():
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert pyproject["project"]["requires-python"] == ">=3.11"


def test_readme_has_exactly_two_commands_and_ci_runs_the_test_one():
    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"```\n(.*?)```", readme, flags=re.S)
    commands = [line for b in blocks for line in b.strip().splitlines() if line.strip()]
    assert len(commands) == 2, commands
    ci = (REPO / ".ci" / "run").read_text()
    assert commands[1] in ci
    assert "snakemake --cores 2" in commands[0]


def _leaves(d, prefix=()):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, prefix + (k,))
        else:
            yield prefix + (k,), v


def test_config_examples_in_the_docs_are_valid_and_stated_defaults_are_the_schemas():
    """Every YAML config block in README.md and docs/*.md passes the schema, and a block the text
    calls "the defaults" holds exactly the schema's defaults (docs/datasets.md once listed a
    synthetic scene's n_frames, fps and yaw period from an older schema)."""
    from stex.config import validate_config

    n_defaults = 0
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = path.read_text()
        for m in re.finditer(r"```yaml\n(.*?)```", text, flags=re.S):
            block = yaml.safe_load(m.group(1))
            validate_config(block)  # raises naming the key of a stale example
            if not text[m.end():m.end() + 200].strip().startswith("These values are the defaults"):
                continue
            n_defaults += 1
            defaults = validate_config({"source": {"kind": block["source"]["kind"]}})
            for keys, value in _leaves(block):
                want = defaults
                for k in keys:
                    want = want[k]
                assert value == want, f"{path.name}: {'.'.join(keys)} is {value!r}, the schema's default {want!r}"
    assert n_defaults >= 1
