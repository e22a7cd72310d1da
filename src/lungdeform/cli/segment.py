"""``lungdeform segment CT --out DIR``: left/right lung masks, volumes and an overlay from a raw CT."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from lungdeform.atomic import jsonable, staged_dir, write_bytes
from lungdeform.errors import InputError
from lungdeform.io.mask import extract_surface
from lungdeform.io.meshfile import write_mesh
from lungdeform.segment import ct as C
from lungdeform.segment import lungs as S
from lungdeform.segment import split as L

from .common import SERIES_DESCRIPTION_HELP, SERIES_HELP, check_output, dicom_input, say, series_choice

MASK_FORMATS = ("nii.gz", "mha")


def register(apps) -> None:
    @apps.root.command("segment")
    def segment_command(
        ct: Path = typer.Argument(..., help="CT in HU (or a binary mask holding both lungs in one label: split into left and right): NIfTI/MHA/NRRD, a DICOM folder (or one of its files, or a parent folder of one series), or a .tar.gz/.zip of one, or a dataset folder holding only such an archive."),
        out: Path = typer.Option(..., "--out", help="Output folder."),
        fmt: str = typer.Option("nii.gz", "--format", help="Mask format: nii.gz or mha."),
        surfaces: bool = typer.Option(False, "--surfaces/--no-surfaces", help="Also build left/right lung surfaces (STL) with lungdeform.io.mask."),
        target_vertices: int = typer.Option(20000, "--target-vertices", help="Vertex budget per surface."),
        downsample: int = typer.Option(1, "--downsample", help="In-plane block-mean factor before segmenting (speed)."),
        series: str = typer.Option(None, "--series", help=SERIES_HELP),
        series_description: str = typer.Option(None, "--series-description", help=SERIES_DESCRIPTION_HELP),
    ) -> None:
        """Segment the lungs (no learned weights), or split a both-lung mask: masks, volumes.json, overlay.png (--surfaces: STL surfaces too)."""


        fmt = fmt.lower().lstrip(".")
        if fmt not in MASK_FORMATS:
            raise InputError(f"--format must be one of {', '.join(MASK_FORMATS)}, got {fmt!r}")
        if downsample < 1:
            raise InputError(f"--downsample must be ≥ 1, got {downsample}")
        check_output(out, [ct], folder=True, writes=[*(f"{s}_lung.{fmt}" for s in ("left", "right")),
                                                      "left_lung.stl", "right_lung.stl", "overlay.png", "volumes.json"])
        choice = series_choice(series, series_description)
        dicom_input(ct, choice)  # what a DICOM folder holds besides the CT, said; several CT series refused
        t0 = time.perf_counter()
        image = L.read_ct_or_mask(ct, series=choice)  # a binary mask holding both lungs is split, not segmented
        t_read = time.perf_counter() - t0
        image, seg = L.segment_ct_or_mask(image, downsample, progress=say)
        t_seg = time.perf_counter() - t0 - t_read
        surf_info, meshes = {}, {}
        if surfaces:  # built before anything is written: a failure leaves no partial output

            for side in ("left", "right"):
                say(f"surface of the {side} lung")
                res = extract_surface(seg.mask_image(side), None, target_vertices=target_vertices, name=f"{side} lung")
                meshes[side] = res.surface
                surf_info[side] = {"vertices": int(len(res.surface.vertices)), "faces": int(len(res.surface.faces)),
                                   "notes": list(res.notes)}
        names = [f"{side}_lung.{fmt}" for side in ("left", "right")] + ["overlay.png"] + \
                [f"{side}_lung.stl" for side in meshes] + ["volumes.json"]
        with staged_dir(out) as folder:  # every output appears at the end, together, or none does
            for side in ("left", "right"):
                C.write_mask(seg.mask_image(side), folder / f"{side}_lung.{fmt}")
            S.overlay_png(seg, folder / "overlay.png")
            for side, surf in meshes.items():
                write_mesh(folder / f"{side}_lung.stl", surf.vertices, surf.faces)
            elapsed = time.perf_counter() - t0
            report = {
                "source": str(ct),
                "grid": {"shape_zyx": list(image.array.shape), "spacing_xyz_mm": image.spacing.tolist(),
                         "downsample": downsample},
                "volumes_ml": seg.volumes_ml,
                "airway_removal": seg.airway_removal,
                "details": seg.details,
                "surfaces": surf_info,
                "timings_s": {"read": t_read, "segment": t_seg, "total": elapsed},
            }
            write_bytes(folder / "volumes.json", (json.dumps(report, indent=2, default=jsonable) + "\n").encode())
        written = [out / name for name in names]
        v = seg.volumes_ml
        typer.echo(f"left lung {v['left']:.0f} mL, right lung {v['right']:.0f} mL, "
                   f"airways removed {v['removed']:.0f} mL (tree {v['airway']:.0f} mL); {elapsed:.1f} s")
        typer.echo(seg.airway_removal)
        for p in written:
            typer.echo(f"wrote {p}")
