"""Blender's own extension validator on what tools/build_extension.py makes.

The validator is ``bl_pkg/cli/blender_ext.py`` from the bpy module, the script
behind ``blender --command extension validate``, given Blender's list of valid
tags as Blender gives it. It checks the staged source tree and every
platform's zip; a manifest it must reject shows it is really checking.

One build of all four platforms per module, offline: tools/bootstrap.sh filled
the wheel cache build/wheels (about 100 MB from PyPI, once), so the tests
never need the network (about 1.5 s).
"""
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tomllib
import types
import zipfile

import pytest

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL_PATH = os.path.join(ROOT, "tools", "build_extension.py")


def _load(name: str, path: str):
    """Import a script that is not in a package, by its path."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


tool = _load("build_extension", TOOL_PATH)


@pytest.fixture(scope="module")
def blender_ext():
    """Blender's extension script as a module (its wheel/platform helpers)."""
    scripts = tool.blender_scripts()
    if scripts is None:
        pytest.skip("no bpy module, so no Blender extension validator")
    return _load("blender_ext", os.path.join(scripts, "addons_core", "bl_pkg", "cli", "blender_ext.py"))


@pytest.fixture(scope="module")
def built(blender_ext, tmp_path_factory):
    """Every platform's zip and the staged tree, built once (the wheel cache is build/wheels)."""
    tmp = tmp_path_factory.mktemp("ext")
    out, stage = tmp / "dist", tmp / "stage"
    r = subprocess.run([sys.executable, TOOL_PATH, "--offline", "--out", str(out), "--stage", str(stage)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    zips = {p: out / tool.zip_name("prtt_addon", _version(), p) for p in tool.PLATFORMS}
    return types.SimpleNamespace(out=out, stage=stage, zips=zips, stdout=r.stdout)


def _version() -> str:
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as f:
        return tomllib.load(f)["version"]


def _validate(path) -> tuple[int, str]:
    rc, out = tool.validate(str(path))
    print(f"--- validate {path}: exit {rc}\n{out}")
    return rc, out


def test_source_tree_passes(built):
    rc, out = _validate(built.stage)
    assert rc == 0, out
    assert "Success parsing TOML" in out


def test_repository_root_passes(blender_ext):
    """``blender_ext.py validate .`` in a checkout, as a contributor runs it."""
    rc, out = _validate(ROOT)
    assert rc == 0, out
    assert "Success parsing TOML" in out


def test_staged_manifest_is_the_repositorys(built):
    """What was validated is the repository's manifest plus platforms and wheels."""
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as f:
        repo = tomllib.load(f)
    with open(built.stage / "blender_manifest.toml", "rb") as f:
        staged = tomllib.load(f)
    assert staged.pop("platforms") == list(tool.PLATFORMS)
    in_zips = set()
    for path in built.zips.values():
        with zipfile.ZipFile(path) as z:
            in_zips |= set(tomllib.loads(z.read("blender_manifest.toml").decode())["wheels"])
    assert set(staged.pop("wheels")) == in_zips
    assert staged == repo


@pytest.mark.parametrize("plat", list(tool.PLATFORMS))
def test_zip_passes(built, plat):
    rc, out = _validate(built.zips[plat])
    assert rc == 0, out
    assert "Success parsing TOML" in out


@pytest.mark.parametrize("plat", list(tool.PLATFORMS))
def test_zip_holds_its_platforms_wheels_only(built, blender_ext, plat):
    """Judged by Blender's own reading of wheel names: every wheel runs on the
    zip's one platform, and each pin is there for Python 3.11 and 3.13."""
    with zipfile.ZipFile(built.zips[plat]) as z:
        man = tomllib.loads(z.read("blender_manifest.toml").decode())
        names = set(z.namelist())
    assert man["platforms"] == [plat]
    wheels = [os.path.basename(w) for w in man["wheels"]]
    assert {f"wheels/{w}" for w in wheels} == {n for n in names if n.startswith("wheels/")}
    for w in wheels:
        assert blender_ext.blender_platform_compatible_with_wheel_platform_from_filepath(plat, w), w
    pins = tool.runtime_pins()
    assert tool.pythons_for(plat) == (["3.11"] if plat == "macos-x64" else ["3.11", "3.13"])
    for python in tool.pythons_for(plat):
        version = tuple(int(x) for x in python.split("."))
        # Blender reads "py3" (a pure-Python wheel) as (3,): any Python 3.
        have = [w for w in wheels if {version, version[:1]} & set(blender_ext.python_versions_from_wheel(w))]
        want = tool.pins_for(pins, python)
        assert sorted(tool._normalise(w.split("-")[0]) + "==" + w.split("-")[1] for w in have) == \
            sorted(tool._normalise(p.split("==")[0]) + "==" + p.split("==")[1] for p in want), (python, have)
        # numba, the bounce's compiled shading, ships for every Blender.
        assert {"numba", "llvmlite"} <= {tool._normalise(w.split("-")[0]) for w in have}, (python, have)


def test_wheel_pins_follow_their_python_markers():
    """Each Python gets one numba (the one its Blender's numpy takes), and a
    marker this build cannot read is refused, not read differently from pip."""
    pins = tool.runtime_pins()
    assert "numba==0.61.2" in tool.pins_for(pins, "3.11") and "numba==0.68.1" not in tool.pins_for(pins, "3.11")
    assert "numba==0.68.1" in tool.pins_for(pins, "3.13") and "numba==0.61.2" not in tool.pins_for(pins, "3.13")
    assert tool.marker_holds("", "3.13") and tool.marker_holds('python_version >= "3.13"', "3.13")
    assert not tool.marker_holds("python_version < '3.13'", "3.13")
    with pytest.raises(SystemExit, match="not supported"):
        tool.marker_holds('sys_platform == "linux"', "3.11")


def test_build_prints_each_zip_and_its_size(built):
    for plat, path in built.zips.items():
        assert re.search(rf"built \S+{re.escape(path.name)}\s+\d+\.\d MB\s+{plat}", built.stdout), built.stdout
        assert re.search(rf"validate \S+{re.escape(path.name)}: ok", built.stdout)
    assert re.search(r"validate \S+stage: ok", built.stdout)


def _bad_manifest(**changes) -> str:
    """The repository's manifest with some top-level string values replaced."""
    with open(os.path.join(ROOT, "blender_manifest.toml"), encoding="utf-8") as f:
        text = f.read()
    for key, value in changes.items():
        text, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.M)
        assert n == 1, key
    return text


def test_validator_rejects_long_tagline_in_a_folder(tmp_path):
    (tmp_path / "__init__.py").write_text("")
    (tmp_path / "blender_manifest.toml").write_text(_bad_manifest(tagline='"' + "x" * 70 + '"'))
    rc, out = _validate(tmp_path)
    assert rc != 0
    assert "no longer than 64 characters expected, found 70" in out


def test_validator_rejects_long_tagline_in_a_zip(built, tmp_path):
    """The archive check is a separate code path in the validator: a copy of a
    built zip with only the tagline changed must fail."""
    src = built.zips["linux-x64"]
    bad = tmp_path / src.name
    with zipfile.ZipFile(src) as z, zipfile.ZipFile(bad, "w") as out:
        for item in z.infolist():
            data = z.read(item)
            if item.filename == "blender_manifest.toml":
                data = re.sub(rb'^tagline = .*$', b'tagline = "' + b"y" * 70 + b'"', data, count=1, flags=re.M)
            out.writestr(item, data)
    rc, out = _validate(bad)
    assert rc != 0
    assert "no longer than 64 characters expected, found 70" in out


def test_validator_checks_tags(tmp_path):
    """The tag list is passed as Blender passes it (standalone the script checks no tags)."""
    (tmp_path / "__init__.py").write_text("")
    (tmp_path / "blender_manifest.toml").write_text(_bad_manifest(tags='["Lighting", "Baking"]'))
    rc, out = _validate(tmp_path)
    assert rc != 0 and '"Baking"' in out


def test_exclusions_match_blenders_builder(blender_ext, tmp_path):
    """The build reads paths_exclude_pattern itself; Blender's builder, given
    the same tree, must pick the very same files."""
    raw = tmp_path / "raw"
    shutil.copytree(os.path.join(ROOT, "prtt_addon"), raw)
    shutil.copytree(os.path.join(ROOT, "shaders"), raw / "shaders")
    shutil.copy(os.path.join(ROOT, "LICENSE"), raw / "LICENSE")
    shutil.copy(os.path.join(ROOT, "blender_manifest.toml"), raw / "blender_manifest.toml")
    # Litter a working tree has.
    for junk in ("__pycache__/x.cpython-311.pyc", "core/__pycache__/y.pyc", "stray.pyc", "core/.DS_Store",
                 ".pytest_cache/README.md", "dev/extra.py"):
        (raw / junk).parent.mkdir(parents=True, exist_ok=True)
        (raw / junk).write_text("junk")
    zip_path = tmp_path / "blender.zip"
    r = subprocess.run([sys.executable, blender_ext.__file__, "build", "--source-dir", str(raw),
                        "--output-filepath", str(zip_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    with zipfile.ZipFile(zip_path) as z:
        blenders = set(z.namelist()) - {"blender_manifest.toml"}
    patterns = tool.read_manifest()[1]["build"]["paths_exclude_pattern"]
    ours = {rel for _, rel in tool.extension_files([(str(raw), "")], patterns)} - {"blender_manifest.toml"}
    assert ours == blenders
    assert {"__init__.py", "worker.py", "LICENSE", "shaders/prtt_common.glsl"} <= ours
    assert not [n for n in ours if n.startswith("dev/") or "__pycache__" in n
                or n.endswith(".pyc") or "/." in "/" + n]


def test_second_build_is_offline(built, tmp_path):
    """The wheel cache has everything: no pip run, even with no index to reach."""
    env = dict(os.environ, PIP_NO_INDEX="1", PIP_INDEX_URL="http://127.0.0.1:9/simple")
    r = subprocess.run([sys.executable, TOOL_PATH, "--out", str(tmp_path / "dist"), "--stage",
                        str(tmp_path / "stage"), "--no-validate"], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "downloading" not in r.stdout
    assert len(list((tmp_path / "dist").glob("*.zip"))) == len(tool.PLATFORMS)


def test_missing_wheel_means_no_zip(built, tmp_path, monkeypatch, capsys):
    """A Python whose wheels PyPI lacks: that platform gets no zip (an old one
    of that name is removed), the build says which wheels and exits 1."""
    plat = "linux-x64"
    monkeypatch.setattr(tool, "PYTHONS", ("3.11", "3.99"))
    monkeypatch.setenv("PIP_NO_INDEX", "1")            # no network needed to find nothing
    out = tmp_path / "dist"
    out.mkdir()
    old = out / tool.zip_name("prtt_addon", _version(), plat)
    old.write_bytes(b"an older build")
    rc = tool.main(["--platform", plat, "--out", str(out), "--stage", str(tmp_path / "stage")])
    err = capsys.readouterr().err
    assert rc == 1
    assert re.search(rf"NOT built: {plat}: no embreex==\S+, OpenEXR==\S+, xatlas==\S+, threadpoolctl==\S+, "
                     rf"numba==0\.68\.1, llvmlite==\S+ wheel "
                     rf"for Python 3.99", err), err
    assert not old.exists() and not list(out.iterdir())


def test_same_zips_as_blenders_split_build(built, blender_ext, tmp_path):
    """``blender --command extension build --split-platforms`` on the staged
    tree (the layout Blender recommends) gives zips of the same names holding
    the same files."""
    r = subprocess.run([sys.executable, blender_ext.__file__, "build", "--split-platforms", "--source-dir",
                        str(built.stage), "--output-dir", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    for path in built.zips.values():
        with zipfile.ZipFile(path) as ours, zipfile.ZipFile(tmp_path / path.name) as blenders:
            assert set(ours.namelist()) == set(blenders.namelist()), path.name


def test_offline_build_names_what_the_cache_lacks(built, tmp_path, monkeypatch, capsys):
    """--offline never runs pip: a wheel missing from the cache fails its
    platform with a message saying how to fill the cache."""
    monkeypatch.setattr(tool, "PYTHONS", ("3.11", "3.99"))
    monkeypatch.setattr(tool, "pip_download", lambda *a, **k: pytest.fail("--offline ran pip"))
    rc = tool.main(["--offline", "--platform", "linux-x64", "--out", str(tmp_path / "dist"),
                    "--stage", str(tmp_path / "stage"), "--no-validate"])
    err = capsys.readouterr().err
    assert rc == 1
    assert "not in the wheel cache" in err and "tools/bootstrap.sh" in err and "Python 3.99" in err
