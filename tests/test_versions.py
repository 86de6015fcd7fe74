"""What every output records of the code that made it: the commit, and whether the package's
files differ from it (the commit alone would then not say what ran)."""

from __future__ import annotations

import subprocess

from hipode_pipeline import machine, versions


def git(folder, *args):
    subprocess.run(
        ["git", "-c", "user.email=t@t", "-c", "user.name=t", *args],
        cwd=folder,
        check=True,
        capture_output=True,
    )


def test_modified_package_files_are_recorded(tmp_path, monkeypatch):
    package = tmp_path / "repo" / "pkg"
    package.mkdir(parents=True)
    (package / "code.py").write_text("x = 1\n")
    (tmp_path / "repo" / "notes.txt").write_text("outside the package\n")
    git(tmp_path / "repo", "init", "-q")
    git(tmp_path / "repo", "add", ".")
    git(tmp_path / "repo", "commit", "-q", "-m", "c")
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))  # no checkout above counts
    monkeypatch.setattr(versions, "PACKAGE_DIR", package)
    assert versions.git_modified() is False
    (tmp_path / "repo" / "notes.txt").write_text("changed, but not the package\n")
    assert versions.git_modified() is False
    (package / "code.py").write_text("x = 2\n")
    assert versions.git_modified() is True
    git(tmp_path / "repo", "checkout", "-q", "--", "pkg")
    (package / "new.py").write_text("y = 1\n")  # untracked code runs too
    assert versions.git_modified() is True
    monkeypatch.setattr(versions, "PACKAGE_DIR", tmp_path / "elsewhere")
    (tmp_path / "elsewhere").mkdir()
    assert versions.git_modified() is None  # not a checkout


def test_every_output_records_it():
    recorded = versions.package_versions()
    assert "git_commit" in recorded and "git_modified" in recorded
    assert recorded["git_modified"] in (True, False, None)


def test_the_cpu_is_named_with_its_generation(tmp_path):
    # two processors' blocks, as /proc/cpuinfo lists them; a VM that names only the brand
    block = "processor\t: {n}\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
    block += "model name\t: AMD EPYC\nstepping\t: 1\nflags\t\t: fpu avx512f\n\n"
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(block.format(n=0) + block.format(n=1).replace(": 17", ": 2"))
    assert machine.cpu_name(cpuinfo) == "AMD EPYC (family 25, model 17, stepping 1)"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: Some CPU\n")
    assert machine.cpu_name(cpuinfo) == "Some CPU"
    assert machine.cpu_name(tmp_path / "absent") != ""
    assert versions.package_versions()["cpu"] == machine.cpu_name()
