"""The one validation walk (lungdeform.io.dicom.attributes): decimal strings, VR limits, required attributes."""

import warnings

import numpy as np
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from lungdeform.errors import InputError, ReadError
from lungdeform.io.dicom.attributes import check_dataset, decimal, require


def test_decimal_strings_fit_16_bytes_and_keep_the_value():
    # why: Eclipse refuses DS values over 16 bytes (PS3.5 6.2); the string must also read back as
    # the number to the precision 16 bytes allow (12 significant digits, fewer for long exponents)
    rng = np.random.default_rng(27)
    values = np.concatenate([rng.normal(0, 1, 200) * 10.0 ** rng.integers(-30, 30, 200),
                             [0.0, -0.0, 1e-300, -1.2345678901234567e-05, -123456789.123456789, 2 ** 60]])
    for x in values:
        text = decimal(x)
        assert len(text.encode()) <= 16, text
        assert float(text) == pytest.approx(x, rel=1e-7, abs=0.0), (x, text)


def test_decimal_refuses_what_is_not_finite():
    with pytest.raises(InputError, match="finite"):
        decimal(float("nan"))


def test_check_dataset_walks_sequences_and_names_the_attribute():
    # a DS value of 17 bytes deep in a sequence, and a malformed UID: refused, never written
    ds = Dataset()
    item = Dataset()
    with warnings.catch_warnings():  # pydicom warns of the long value it holds: the walk must refuse it
        warnings.simplefilter("ignore")
        item.ContourData = ["1.2345678901234567", "0", "0"]
    ds.ROIContourSequence = Sequence([item])
    with pytest.raises(InputError, match=r"ROIContourSequence\[0\].*ContourData.*16 bytes"):
        check_dataset(ds, "rs.dcm")
    ok = Dataset()
    ok.SliceThickness = decimal(1 / 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ok.SOPInstanceUID = "1.2.3.04"  # a leading zero (PS3.5 9.1)
    with pytest.raises(InputError, match="SOPInstanceUID.*not a DICOM UID"):
        check_dataset(ok)
    ok.SOPInstanceUID = "1.2.3.4"
    check_dataset(ok)


def test_require_names_what_is_missing_and_bad_uids():
    ds = Dataset()
    ds.SOPInstanceUID = "1.2.3"
    with pytest.raises(ReadError, match="f.dcm: DICOM file lacks FrameOfReferenceUID, which X needs"):
        require(ds, ("SOPInstanceUID", "FrameOfReferenceUID"), "f.dcm", "which X needs")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.FrameOfReferenceUID = "1.2.x"
    with pytest.raises(ReadError, match="FrameOfReferenceUID '1.2.x' is not a DICOM UID"):
        require(ds, ("SOPInstanceUID", "FrameOfReferenceUID"), "f.dcm", "which X needs")


def test_decimal_keeps_the_places_asked_for_while_they_fit():
    # positions are written with 6 decimals as before (the grid read back unchanged); a value too
    # long for that falls back to significant digits within 16 bytes
    assert decimal(-166.0, places=6) == "-166.000000" and decimal(4.800000190734863, 6) == "4.8"
    assert decimal(-123456789.123456, places=6) == "-123456789.123"  # 12 significant digits


def test_declare_charset_says_utf8_only_for_text_that_is_not_ascii(tmp_path):
    # why: a CT phase or REG copied a Latin-1 source's "Müller^Jürgen" without SpecificCharacterSet,
    # so the file held bytes outside the default repertoire (dciodvfy: an error). Truth: pydicom's
    # own bytes on disk are the UTF-8 encoding once it is declared; ASCII text declares nothing
    import io

    from pydicom import dcmread
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    from lungdeform.io.dicom.attributes import declare_charset

    plain = Dataset()
    plain.PatientName = "Doe^Jane"
    declare_charset(plain)
    assert "SpecificCharacterSet" not in plain
    ds = Dataset()
    ds.PatientName, ds.PatientID = "Doe^Jane", "1"
    item = Dataset()
    item.ROIName = "Tumör"  # in a sequence: the walk goes into it
    ds.StructureSetROISequence = Sequence([item])
    declare_charset(ds)
    assert ds.SpecificCharacterSet == "ISO_IR 192"
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    buf = io.BytesIO()
    ds.save_as(buf)
    assert "Tumör".encode() in buf.getvalue()
    assert dcmread(io.BytesIO(buf.getvalue()), force=True).StructureSetROISequence[0].ROIName == "Tumör"


def test_fit_text_cuts_on_character_boundaries_within_the_vr():
    # why: a StructureSetLabel (SH) derived from "GTV_β肿瘤 moved" was 20 bytes of UTF-8, refused at
    # the end of a track run (issue 36). Truth: the UTF-8 length of the result (what dciodvfy counts)
    # is within the VR's bytes, the result is a prefix of the text that decodes (no half character)
    # and never ends before a combining mark (e + U+0301 stays é), a variation selector or a joiner
    from lungdeform.io.dicom.attributes import fit_text

    assert fit_text("GTV", "SH") == "GTV"  # ASCII within the limit: as it is
    assert fit_text("GTV_β肿瘤 moved", "SH") == "GTV_β肿瘤 mov"  # 16 bytes: 4 + 2 + 3 + 3 + 4
    assert len("GTV_β肿瘤 mov".encode()) == 16
    for text in ("肿瘤" * 20, "όγκος" * 10, "ورم_رئوي" * 8, "e\u0301" * 30, "x\u200dy " * 20, "a\ufe0f" * 40):
        for vr in ("SH", "LO"):
            out = fit_text(text, vr)
            assert len(out.encode()) <= {"SH": 16, "LO": 64}[vr] and text.startswith(out) and out
            rest = text[len(out):]
            assert not rest or not (rest[0] in "\u0301\u200d\ufe0f" or out.endswith("\u200d")), (text, out)
    # a tag kept whole at the end, the base cut; control characters and the backslash replaced
    assert fit_text("β" * 40, "LO", keep="@phase03") == "β" * 28 + "@phase03"
    assert fit_text("a\\b\tc", "LO") == "a_b_c"
    # kept unique among values already taken
    taken = {fit_text("肿瘤" * 20, "SH")}
    second = fit_text("肿瘤" * 21, "SH", taken=taken)
    assert second not in taken and second.endswith("~2") and len(second.encode()) <= 16


def test_a_latin1_value_that_fits_only_in_latin1_keeps_latin1():
    # a copied Latin-1 description of 40 "Ü" is 40 bytes in ISO_IR 100 but 80 in UTF-8, over LO's 64:
    # declared as UTF-8 the valid source would be refused; Latin-1 is declared instead and the value
    # fits (measured in the declared character set). Text Latin-1 cannot hold stays UTF-8.
    from lungdeform.io.dicom.attributes import declare_charset

    ds = Dataset()
    ds.StudyDescription, ds.PatientName = "Ü" * 40, "Müller^Jürgen"
    declare_charset(ds)
    assert ds.SpecificCharacterSet == "ISO_IR 100"
    check_dataset(ds)
    short = Dataset()
    short.PatientName = "Müller^Jürgen"
    declare_charset(short)
    assert short.SpecificCharacterSet == "ISO_IR 192"  # fits in UTF-8: UTF-8, as before
    mixed = Dataset()
    mixed.StudyDescription, mixed.SeriesDescription = "Ü" * 40, "肿瘤"
    declare_charset(mixed)
    assert mixed.SpecificCharacterSet == "ISO_IR 192"
    with pytest.raises(InputError, match="StudyDescription .* longer than 64 bytes"):
        check_dataset(mixed)
