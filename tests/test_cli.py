"""The `sgjax` command line, run in-process and as a real subprocess."""

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from sgjax.geometry import pointcloud
from sgjax_cli import main


def test_example_then_fit_json_and_mesh(tmp_path, capsys):
    cloud = tmp_path / "box.npy"
    assert main(["example", str(cloud), "--shape", "box"]) == 0
    assert np.load(cloud).shape == (800, 3)
    capsys.readouterr()
    mesh_path = tmp_path / "fit.ply"
    assert main(["fit", str(cloud), "--json", "--mesh", str(mesh_path)]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(record) == {"file", "scale", "epsilon", "rotation", "translation", "inlier_ratio", "valid"}
    assert record["valid"] and len(record["scale"]) == 3 and np.array(record["rotation"]).shape == (3, 3)
    # the example box has semi-axes (0.04, 0.02, 0.06)
    np.testing.assert_allclose(sorted(record["scale"]), [0.02, 0.04, 0.06], rtol=0.1)
    mesh = trimesh.load(mesh_path)
    assert mesh.is_watertight and len(mesh.faces) > 100


def _write_ascii_pcd(path, pts):
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\nDATA ascii\n"
    )
    path.write_text(header + "\n".join(" ".join(f"{v:.7g}" for v in p) for p in pts) + "\n")


def test_reads_ply_and_pcd(tmp_path, capsys):
    cloud = tmp_path / "c.npy"
    main(["example", str(cloud), "--shape", "ellipsoid"])
    pts = np.load(cloud).astype(np.float64)
    trimesh.PointCloud(pts).export(tmp_path / "c.ply")
    _write_ascii_pcd(tmp_path / "c.pcd", pts)
    capsys.readouterr()
    try:
        import open3d  # noqa: F401
    except ImportError:  # e.g. no libusb-1.0 on this machine: .ply still works, .pcd says why it cannot
        assert main(["fit", str(tmp_path / "c.ply"), "--json"]) == 0
        assert len(capsys.readouterr().out.strip().splitlines()) == 1
        with pytest.raises(pointcloud.CloudError, match="needs open3d.*libusb-1.0"):
            pointcloud.load_cloud(str(tmp_path / "c.pcd"))
        return
    assert main(["fit", str(tmp_path / "c.ply"), str(tmp_path / "c.pcd"), "--json"]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert len(records) == 2
    np.testing.assert_allclose(records[0]["scale"], records[1]["scale"], rtol=1e-3)


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("missing.npy", None, "no such file"),
        ("bad.npy", b"not a numpy file", "cannot read"),
        ("bad.pcd", b"garbage", "not a PCD file"),
        ("cloud.xyz", b"1 2 3", "unsupported extension"),
        ("flat.npy", "flat", "coplanar"),
        ("few.npy", "few", "too few points"),
    ],
)
def test_bad_files_give_a_message_and_a_nonzero_exit(tmp_path, capsys, name, content, message):
    path = tmp_path / name
    if content == "flat":
        np.save(path, np.c_[np.random.default_rng(0).normal(size=(50, 2)), np.zeros(50)])
    elif content == "few":
        np.save(path, np.random.default_rng(0).normal(size=(5, 3)))
    elif content is not None:
        path.write_bytes(content)
    assert main(["fit", str(path)]) == 2
    assert message in capsys.readouterr().err


def test_console_entry_point_runs_as_a_process(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "sgjax_cli", "fit", str(tmp_path / "nothing.npy")], capture_output=True, text=True
    )
    assert out.returncode == 2 and "no such file" in out.stderr


def test_build_db_then_candidates_json_and_png(tmp_path, capsys):
    db_path = tmp_path / "db.npz"
    assert main(["build-db", "--small", "--out", str(db_path), "--workers", "2"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["primitives"] > 20 and set(summary["per_family"]) == {"cuboid", "cylinder", "frustum", "elliptical_cylinder"}
    assert main(["build-db", "--small", "--out", str(db_path)]) == 0  # present: loaded, not rebuilt
    assert "already built" in capsys.readouterr().out

    cloud = tmp_path / "box.npy"
    main(["example", str(cloud), "--shape", "cylinder"])
    capsys.readouterr()
    png = tmp_path / "cands.png"
    assert main(["candidates", str(cloud), "--db", str(db_path), "--json", "--top", "3", "--png", str(png)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["count"] > 0 and len(out["grasps"]) == 3 and out["reason"] is None
    g = out["grasps"][0]
    assert np.array(g["pose"]).shape == (4, 4) and 0 < g["width"] <= 0.08
    assert png.stat().st_size > 10_000

    assert main(["candidates", str(cloud), "--db", str(db_path)]) == 0
    assert "candidates" in capsys.readouterr().out


def test_candidates_bad_input_exits_2(tmp_path, capsys):
    bad = tmp_path / "nan.npy"
    np.save(bad, np.full((100, 3), np.nan))
    assert main(["candidates", str(bad), "--db", str(tmp_path / "none.npz")]) == 2
    assert "NaN" in capsys.readouterr().err
    good = tmp_path / "c.npy"
    main(["example", str(good)])
    assert main(["candidates", str(good), "--db", str(tmp_path / "none.npz")]) == 2
    assert "sgjax build-db" in capsys.readouterr().err


@pytest.mark.parametrize(
    "options, message",
    [
        (["--per-source", "stage1"], "is not SOURCE=COUNT"),
        (["--per-source", "stage1=4,grasps=2"], "unknown candidate source 'grasps'"),
        (["--targets-per-scene", "0"], "targets_per_scene must be >= 1"),
        (["--per-source", "stage1_relabel=4"], "stage1_relabel only names samples of directories labelled by earlier"),
    ],
)
def test_label_options_are_checked_before_any_work(tmp_path, capsys, options, message):
    assert main(["label", "--scenes", "1", "--out", str(tmp_path / "labels"), *options]) != 0
    assert message in capsys.readouterr().err
    assert not (tmp_path / "labels").exists()


def test_baselines_setup_arguments_and_bad_input(tmp_path, capsys):
    """`sgjax baselines setup`: argparse rejects a missing or unknown baseline; bad options fail with a
    message before anything is created."""
    for argv, message in ((["baselines", "setup"], "the following arguments are required: baseline"),
                          (["baselines", "setup", "gpd"], "invalid choice: 'gpd'")):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2 and message in capsys.readouterr().err
    prefix = tmp_path / "env"
    assert main(["baselines", "setup", "contact-graspnet", "--prefix", str(prefix), "--jobs", "0"]) == 1
    assert "max_jobs must be >= 1, got 0" in capsys.readouterr().err and not prefix.exists()
    done = subprocess.run([sys.executable, "-m", "sgjax_cli", "baselines", "setup", "contact-graspnet", "--prefix",
                           str(prefix), "--python", str(tmp_path / "no-python")], capture_output=True, text=True)
    assert done.returncode == 1 and f"cannot run '{tmp_path / 'no-python'}' to create the venv" in done.stderr
    assert not prefix.exists()


def test_baselines_setup_rerun_skips_a_finished_environment(capsys):
    """On a finished environment (here: the default one, when it exists) the setup skips every step and
    only probes the checkpoint again."""
    from eval import cgn_setup

    if cgn_setup.installed_python() is None:
        pytest.skip("no Contact-GraspNet environment at the default location: run `sgjax baselines setup contact-graspnet`")
    assert main(["baselines", "setup", "contact-graspnet"]) == 0
    out = capsys.readouterr().out
    assert out.count("[skip]") == 5 and "[run ] probe" in out and "pip install" not in out
    assert "finds this environment by default" in out and cgn_setup.state() == "ready"
