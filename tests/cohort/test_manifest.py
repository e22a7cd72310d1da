"""The cohort manifest: grouping into jobs (order by volume, 'both' → two jobs, paths relative to
the manifest) and every kind of bad input reported at once, naming the manifest and the rows."""

from pathlib import Path

import pytest

from lungdeform.cohort.manifest import check_manifest, read_manifest
from lungdeform.errors import InputError


def _files(folder: Path, *names: str) -> None:
    for name in names:
        p = folder / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")  # the manifest check looks at existence only, never at content


def _manifest(folder: Path, text: str, name: str = "cohort.csv") -> Path:
    p = folder / name
    p.write_text(text.strip() + "\n")
    return p


def test_jobs_grouped_ordered_by_volume_and_both_expanded(tmp_path):
    _files(tmp_path, "P01/a.ply", "P01/b.ply", "P01/c.ply", "P02/ee.nii.gz", "P02/ei.nii.gz",
           "P01/a.pts", "P01/b.pts", "P01/c.pts")
    # rows deliberately not in volume order: the job must follow the volumes, not the rows
    m = read_manifest(_manifest(tmp_path, """
subject,side,volume_ml,path,landmarks
P01,right,2900,P01/c.ply,P01/c.pts
P01,right,2300,P01/a.ply,P01/a.pts
P01,right,2600,P01/b.ply,P01/b.pts

P02,both,3100,P02/ei.nii.gz,
P02,both,2500,P02/ee.nii.gz,
"""))
    assert [j.key for j in m.jobs] == ["P01/right", "P02/left", "P02/right"]
    p01 = m.jobs[0]
    assert p01.volumes_ml == [2300.0, 2600.0, 2900.0]
    assert [p.name for p in p01.inputs] == ["a.ply", "b.ply", "c.ply"]
    assert [p.name for p in p01.landmarks] == ["a.pts", "b.pts", "c.pts"]
    assert p01.rows == [3, 4, 2]  # spreadsheet rows: the header is row 1
    assert all(p.is_absolute() and p.is_file() for p in p01.inputs)  # resolved against the manifest folder
    left, right = m.jobs[1:]
    assert left.inputs == right.inputs and [p.name for p in left.inputs] == ["ee.nii.gz", "ei.nii.gz"]
    assert left.landmarks is None and left.ordered_by == "volume" and m.notes == ()


def test_empty_volumes_keep_row_order_and_say_so(tmp_path):
    _files(tmp_path, "s/2.ply", "s/1.ply")
    m = read_manifest(_manifest(tmp_path, """
subject,side,volume_ml,path
S,left,,s/2.ply
S,left,,s/1.ply
"""))
    job = m.jobs[0]
    assert job.ordered_by == "row" and job.volumes_ml is None
    assert [p.name for p in job.inputs] == ["2.ply", "1.ply"]
    assert len(m.notes) == 1 and "row order" in m.notes[0] and "S left" in m.notes[0]


def test_absolute_paths_and_header_case(tmp_path):
    _files(tmp_path, "data/a.ply", "data/b.ply")
    sub = tmp_path / "manifests"
    sub.mkdir()
    m = read_manifest(_manifest(sub, f"""
Subject , SIDE,Volume_ml,PATH
X,left,1,{tmp_path / 'data/a.ply'}
X,left,2,../data/b.ply
"""))
    assert [p.name for p in m.jobs[0].inputs] == ["a.ply", "b.ply"]


@pytest.mark.parametrize("text, rows, fragment", [
    ("subject,side,path\nA,left,a.ply", "row 1", "missing column(s) volume_ml"),
    ("subject,side,volume_ml,path,notes\nA,left,1,a.ply,x", "row 1", "unknown column(s) 'notes'"),
    ("subject,side,volume_ml,path,path\nA,left,1,a.ply,a.ply", "row 1", "repeated column(s) path"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,2,nope.ply", "row 3", "nope.ply: no such file"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,1,b.ply", "rows 2, 3", "volume 1 mL listed twice"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,2,a.ply", "rows 2, 3", "a.ply listed twice"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,2 L,b.ply", "row 3", "'2 L' is not a number"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,-2,b.ply", "row 3", "must be a positive number"),
    ("subject,side,volume_ml,path\nA,lft,1,a.ply\nA,left,2,b.ply", "row 2", "side 'lft' is not left, right or both"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply", "row 2", "1 scan; a fit needs two or more"),
    ("subject,side,volume_ml,path\nA,both,1,a.nii.gz\nA,left,2,b.ply", "rows 2, 3", "mixes side 'both'"),
    ("subject,side,volume_ml,path,landmarks\nA,left,1,a.ply,a.pts\nA,left,2,b.ply,", "rows 2, 3",
     "landmarks given on rows 2 but not on rows 3"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,,b.ply", "rows 2, 3", "volume_ml given on rows 2 but empty"),
    ("subject,side,volume_ml,path\nA,both,1,a.nii.gz\nA,both,2,b.ply", "row 3", "side 'both' needs a CT"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\nA,left,2,a.pts", "row 3", "not a surface"),
    ("subject,side,volume_ml,path\n../A,left,1,a.ply\nA,left,2,b.ply\nA,left,3,a.ply", "row 2",
     "not a usable folder name"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply\na,left,2,b.ply", "rows 2, 3", "differ only in letter case"),
    ("subject,side,volume_ml,path\nA,left,1,a.ply,extra\nA,left,2,b.ply", "row 2", "5 fields, the header has 4"),
    ("subject,side,volume_ml,path", None, "no scans listed"),
    ("", None, "empty: no header row"),
])
def test_each_problem_named_with_its_rows(tmp_path, text, rows, fragment):
    _files(tmp_path, "a.ply", "b.ply", "a.nii.gz", "b.nii.gz", "a.pts")
    path = tmp_path / "m.csv"
    path.write_text(text + "\n" if text else "")
    with pytest.raises(InputError) as info:
        read_manifest(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: 1 problem in the cohort manifest: ")
    assert fragment in msg
    if rows:
        assert f"{rows}: " in msg


def test_all_problems_reported_at_once(tmp_path):
    # four independent problems in one file: one error lists them all, each with its rows, in row order
    _files(tmp_path, "a.ply", "b.ply", "c.ply")
    path = _manifest(tmp_path, """
subject,side,volume_ml,path
A,left,1,a.ply
A,left,2,missing.ply
B,right,abc,b.ply
B,right,3,c.ply
C,left,1,c.ply
D,up,1,a.ply
D,up,2,b.ply
""")
    manifest, problems = check_manifest(path)
    assert manifest is None
    assert [str(p).split(":")[0] for p in problems] == ["row 3", "row 4", "row 6", "row 7", "row 8"]
    with pytest.raises(InputError, match=r"5 problems") as info:
        read_manifest(path)
    msg = str(info.value)
    assert "\n" not in msg
    for fragment in ("missing.ply: no such file", "'abc' is not a number", "subject C left: 1 scan",
                     "side 'up'"):
        assert fragment in msg
    # B's bad volume is reported once: its job is not also judged on scan count or volumes
    assert "subject B" not in msg


def test_missing_or_unreadable_manifest(tmp_path):
    with pytest.raises(InputError, match=r"nope\.csv: 1 problem in the cohort manifest: no such file"):
        read_manifest(tmp_path / "nope.csv")
    bad = tmp_path / "latin1.csv"
    bad.write_bytes("subject,side,volume_ml,path\nJos\xe9,left,1,a.ply\n".encode("latin-1"))
    with pytest.raises(InputError, match="not UTF-8"):
        read_manifest(bad)


@pytest.mark.parametrize("column", ["path", "landmarks"])
def test_unusable_file_names_are_problems(tmp_path, column):
    # why: a NUL byte or "~nosuchuser" (found by tests/fuzz/fuzz_manifest.py) or a 300-character name
    # make the file system calls raise ValueError / RuntimeError / OSError; each must become a problem
    # of its row, not a crash
    (tmp_path / "a.ply").write_bytes(b"x")
    for bad in ("a\x00.ply", "~nosuchuser9f3/a.ply", "x" * 300 + ".ply"):
        path, landmarks = (bad, "") if column == "path" else ("a.ply", bad)
        rows = f"P01,left,2300,{path},{landmarks}\nP01,left,2900,a.ply,\n"
        (tmp_path / "m.csv").write_text("subject,side,volume_ml,path,landmarks\n" + rows)
        with pytest.raises(InputError, match=rf"row 2: {column} .*not a usable file name"):
            read_manifest(tmp_path / "m.csv")


def test_one_row_naming_a_4dct_folder_is_a_job(tmp_path):
    # a folder on its own row is a 4-D CT: one job per side, its phases read by the fit; with a volume
    # (its volumes are measured per phase) it is refused, naming the row; a lone file still is
    (tmp_path / "P01" / "ct4d").mkdir(parents=True)
    _files(tmp_path, "P02/a.ply")
    m = read_manifest(_manifest(tmp_path, "subject,side,volume_ml,path\nP01,both,,P01/ct4d"))
    assert [(j.subject, j.side, j.inputs) for j in m.jobs] == [
        ("P01", side, [tmp_path / "P01" / "ct4d"]) for side in ("left", "right")]
    with pytest.raises(InputError) as e:
        read_manifest(_manifest(tmp_path, "subject,side,volume_ml,path\nP01,right,2000,P01/ct4d\nP02,left,,P02/a.ply"))
    assert "row 2" in str(e.value) and "leave volume_ml and landmarks empty" in str(e.value)
    assert "row 3" in str(e.value) and "1 scan" in str(e.value)
