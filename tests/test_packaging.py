"""The pip package and the conda environment list the same dependencies."""
import re
import tomllib

import yaml

from conftest import REPO


def _name(req: str) -> str:
    return re.split(r"[<>=!~ \[;]", req.strip(), maxsplit=1)[0].lower().replace("_", "-")


# the system libraries Open3D's wheel links (libEGL, libGL, libusb), which a conda environment must bring
OPEN3D_SYSTEM_LIBS = {"libegl", "libgl", "libusb"}


def test_conda_env_matches_pyproject():
    """The workflow's conda environment holds the package's dependencies and the [scan] extra:
    rules scan and template import Open3D (template.from_scan, template.align)."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    pip_names = {_name(r) for r in pyproject["project"]["dependencies"]}
    pip_names |= {_name(r) for r in pyproject["project"]["optional-dependencies"]["scan"]} | OPEN3D_SYSTEM_LIBS
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
    blocks = re.findall(r"^```\n(.*?)^```$", readme, flags=re.S | re.M)  # unindented, no language
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
    from stex.config import DATASET_KEYS, validate_config

    n_defaults = 0
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = path.read_text()
        for m in re.finditer(r"```yaml\n(.*?)```", text, flags=re.S):
            block = yaml.safe_load(m.group(1))
            if "scene_files" in block:  # a dataset file (workflow/dataset.smk): its shared settings
                assert set(block) <= DATASET_KEYS, block
                validate_config(block.get("common") or {})
                continue
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


def test_an_installed_wheel_has_its_schema_outside_the_checkout(tmp_path):
    """``pip install stex`` (a wheel, not the editable checkout) gives working stage functions: they
    read their defaults from the schema, which once lived outside the package (config/), so every
    stage of an installed wheel failed with FileNotFoundError."""
    import shutil
    import subprocess
    import sys
    import zipfile

    src = tmp_path / "src"  # a copy, so that the build leaves nothing in the checkout
    shutil.copytree(REPO / "stex", src / "stex", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, src / name)
    run = dict(check=True, capture_output=True, text=True, cwd=tmp_path)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                    "-w", str(tmp_path / "dist"), str(src)], **run)
    wheel = next((tmp_path / "dist").glob("stex-*.whl"))
    assert "stex/schema.yaml" in zipfile.ZipFile(wheel).namelist()

    # the dependencies from this machine, stex only from the wheel
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(tmp_path / "venv")], **run)
    python = tmp_path / "venv" / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], **run)
    out = subprocess.run([str(python), "-c", (
        "import stex, stex.config as c\n"
        "print(stex.__file__)\n"
        "for s in c.load_schema()['properties']:\n"
        "    if c.load_schema()['properties'][s].get('type') == 'object': c.section_params(s)\n"
        "print(c.section_params('masks')['depth_far_m'])\n")],
        env={"PATH": str(python.parent)}, **run).stdout.split()
    assert str(tmp_path / "venv") in out[0] and "site-packages" in out[0], out
    assert float(out[1]) > 0


# what a copy of the checkout leaves out: version control, run outputs, caches, build outputs
_NOT_SOURCES = (".git", "results", ".snakemake", "__pycache__", "*.egg-info", "build", "dist",
                ".pytest_cache", ".benchmarks", "*.partial", "*.partial-*", "report.html")


def test_the_sdist_has_an_spdx_license_and_runs_the_tests(tmp_path):
    """``python -m build --sdist``: the license as an SPDX expression with its file (PEP 639; the
    table form is deprecated), and everything the tests read (tests/, the workflow, configs,
    profiles, docs, the conda environment, the CI script), so that tests run from the unpacked
    sdist. It once lacked tests/conftest.py, tests/fake_slurm.py and tests/tiny_synthetic.yaml."""
    import shutil
    import subprocess
    import sys
    import tarfile

    src = tmp_path / "src"  # a copy, so that the build leaves nothing in the checkout
    shutil.copytree(REPO, src, symlinks=True, ignore=shutil.ignore_patterns(*_NOT_SOURCES))
    subprocess.run([sys.executable, "-m", "build", "--sdist", "--outdir", str(tmp_path / "dist"), str(src)],
                   check=True, capture_output=True, text=True)
    sdist = next((tmp_path / "dist").glob("stex-*.tar.gz"))
    with tarfile.open(sdist) as tar:
        top = tar.getnames()[0].split("/")[0]
        names = {n.removeprefix(top + "/") for n in tar.getnames()}
        pkg_info = tar.extractfile(f"{top}/PKG-INFO").read().decode()
        tar.extractall(tmp_path, filter="data")
    assert "License-Expression: MIT" in pkg_info and "License-File: LICENSE" in pkg_info, pkg_info[:2000]
    assert not re.search(r"^License: ", pkg_info, flags=re.M)  # the deprecated field
    needed = {"LICENSE", "README.md", "Snakefile", "pyproject.toml", ".ci/run",
              "tests/conftest.py", "tests/fake_slurm.py", "tests/tiny_synthetic.yaml",
              "profiles/default/config.yaml", "profiles/slurm/config.yaml"}
    for folder in ("tests", "workflow", "config", "envs", "docs", "benchmarks", "stex"):
        needed |= {str(p.relative_to(src)) for p in (src / folder).rglob("*") if p.is_file()}
    assert not needed - names, sorted(needed - names)
    # from the unpacked sdist: the tests that read the README, the CI script, envs/ and the docs
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
                          "tests/test_packaging.py", "-k", "conda_env or readme or config_examples"],
                         cwd=tmp_path / top, capture_output=True, text=True)
    assert run.returncode == 0 and "3 passed" in run.stdout, run.stdout[-3000:] + run.stderr[-2000:]


def test_the_workflow_files_are_formatted_with_snakefmt():
    """``snakefmt --check`` (the settings in pyproject.toml) finds nothing to change in the
    Snakefile and the workflow's .smk files."""
    import subprocess
    import sys

    files = [REPO / "Snakefile", *sorted((REPO / "workflow").glob("*.smk")),
             *sorted((REPO / "workflow" / "rules").glob("*.smk"))]
    run = subprocess.run([sys.executable, "-m", "snakefmt", "--check", *map(str, files)],
                         cwd=REPO, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-4000:]
    assert f"{len(files)} file(s) would be left unchanged" in run.stderr, run.stderr[-2000:]
