"""The DICOM byte guard (lungdeform.io.dicom.guard): damaged element headers refused before GDCM parses a file."""

from __future__ import annotations

import pytest

from lungdeform.errors import ReadError
from lungdeform.io.image import read_image
from tests.io.test_image import _tiny_series


def test_damaged_dicom_element_headers_are_refused(tmp_path):
    # found by tests/fuzz/fuzz_image_dicom.py: a slice whose TransferSyntaxUID's VR reads "UK" (one byte
    # off "UI") was parsed by GDCM with lengths read from the wrong bytes (2.4 GB allocated, 2 s for a
    # 910-byte file) and then silently left out of its series. Each damaged header is refused, naming the
    # file: an unknown VR, and a value length larger than the file (MediaStorageSOPClassUID claiming 32767 bytes)
    from lungdeform.io.dicom.fourdct import read_phases
    from lungdeform.io.dicom.guard import check_dicom_file

    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.11", 4)
    check_dicom_file(tmp_path / "ct" / "11_000.dcm")  # an intact slice passes
    victim = tmp_path / "ct" / "11_002.dcm"
    data = victim.read_bytes()
    at = data.index(b"\x02\x00\x10\x00UI")  # (0002,0010) TransferSyntaxUID, explicit VR "UI"
    victim.write_bytes(data[:at + 4] + b"UK" + data[at + 6:])
    with pytest.raises(ReadError, match=r"11_002.dcm: damaged DICOM file: element \(0002,0010\) .* \(b'UK'\)"):
        read_image(tmp_path / "ct")
    with pytest.raises(ReadError, match="11_002.dcm: damaged DICOM file"):
        read_phases(tmp_path / "ct")
    at = data.index(b"\x02\x00\x02\x00UI")  # (0002,0002) MediaStorageSOPClassUID: its 2-byte length
    victim.write_bytes(data[:at + 6] + b"\xff\x7f" + data[at + 8:])
    with pytest.raises(ReadError, match=r"element \(0002,0002\) at byte \d+ claims 32767 bytes"):
        read_image(tmp_path / "ct" / "11_000.dcm")


def test_damaged_dicom_file_without_preamble_is_refused(tmp_path):
    # found by tests/fuzz/fuzz_image_dicom.py: a slice cut before its preamble (it starts with an
    # explicit-VR element, which GDCM reads too) whose pixel data claims more bytes than are left took
    # GDCM 1.5 s and 1 GB; its element headers are now walked from byte 0 and the damage named
    from lungdeform.io.dicom.guard import check_dicom_file

    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.12", 4)
    victim = tmp_path / "ct" / "12_002.dcm"
    data = victim.read_bytes()[132:]  # no preamble, no "DICM": the file meta group first
    victim.write_bytes(data)
    check_dicom_file(victim)  # intact without its preamble: passes
    victim.write_bytes(data[:-10])  # the pixel data now claims 10 bytes more than are left
    with pytest.raises(ReadError, match=r"12_002.dcm: damaged DICOM file: element \(7FE0,0010\) at byte \d+ claims"):
        read_image(tmp_path / "ct")


def test_dicom_without_preamble_walked_as_implicit_vr(tmp_path):
    # found by tests/fuzz/fuzz_image_dicom.py (libFuzzer out-of-memory): 65 bytes with no preamble and
    # no explicit VR at bytes 4-5 were left to GDCM, which read a 3.3 GB value length and took 4 s and
    # 3.3 GB before failing. Such a file is now walked as implicit VR little endian (the default
    # transfer syntax): a meta-group element without a VR, or a length past the end, is named
    from lungdeform.io.dicom.guard import check_dicom_file

    bad = tmp_path / "implicit.dcm"
    bad.write_bytes(b"\x02\x00\x00UI\x12" + b"\xc6" * 57 + b"<\x00")
    with pytest.raises(ReadError, match=r"implicit.dcm is not a readable DICOM image slice: no preamble, and read as "
                                        r"implicit VR its element \(0002,5500\) at byte 0 has no valid value representation"):
        check_dicom_file(bad)
    # an implicit-VR data set element (group 0008) claiming 3.3 GB of a 20-byte file
    bad.write_bytes(b"\x08\x00\x16\x00" + b"\xc6\xc6\xc6\xc6" + bytes(12))
    with pytest.raises(ReadError, match=r"element \(0008,0016\) at byte 0 claims 3334915782 bytes, 12 are left"):
        check_dicom_file(bad)
    # found by the same fuzzer: (0000,0000), a network command group, first in a file made GDCM take
    # 4 GB for 828 bytes; no file starts with groups 0000-0007
    bad.write_bytes(b"\x00\x00\x00\x00OB\x00\x00\x02\x00\x00\x00\x00\x01" + bytes(12))
    with pytest.raises(ReadError, match=r"implicit.dcm is not a readable DICOM image slice: no preamble, and its first element \(0000,0000\)"):
        check_dicom_file(bad)
    # a sound implicit-VR element passes (its length fits)
    bad.write_bytes(b"\x08\x00\x16\x00\x04\x00\x00\x001.2\x00")
    check_dicom_file(bad)


def test_dicom_meta_group_must_follow_the_preamble(tmp_path):
    # found by tests/fuzz/fuzz_image_dicom.py (libFuzzer out-of-memory): a slice whose first element
    # after "DICM" was (000A,0000) instead of the file meta group made GDCM take 600 MB for 912 bytes;
    # PS3.10 7.1 puts the file meta information right after the preamble
    from lungdeform.io.dicom.guard import check_dicom_file

    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.13", 2)
    victim = tmp_path / "ct" / "13_001.dcm"
    data = victim.read_bytes()
    assert data[132:134] == b"\x02\x00"
    check_dicom_file(victim)  # intact: passes
    victim.write_bytes(data[:132] + b"\x0a\x00" + data[134:])
    with pytest.raises(ReadError, match="must follow the preamble"):
        check_dicom_file(victim)
    with pytest.raises(ReadError, match=r"13_001.dcm: damaged DICOM file: element \(000A,0000\) at byte 132: "
                                        r"the file meta information \(group 0002\) must follow the preamble"):
        read_image(tmp_path / "ct")


def test_dicom_pixel_module_that_overflows_is_refused(tmp_path):
    # found by tests/fuzz/fuzz_image_dicom.py (libFuzzer deadly signal): BitsAllocated 24 and
    # BitsStored 2064 over 16-bit pixel data made GDCM write past its buffer ("corrupted size vs.
    # prev_size": the process died). The pixel module's numbers are checked against each other and
    # against the pixel data's length before GDCM reads the file
    from lungdeform.io.dicom.guard import check_dicom_file

    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.14", 2)
    victim = tmp_path / "ct" / "14_001.dcm"
    data = victim.read_bytes()
    check_dicom_file(victim)  # intact: passes
    # (0028,0100) BitsAllocated and (0028,0101) BitsStored: an 8-byte header (explicit VR US, or
    # implicit VR), then the 2-byte value
    ba = data.index(b"\x28\x00\x00\x01", 132)
    bs = data.index(b"\x28\x00\x01\x01", 132)
    victim.write_bytes(data[:ba + 8] + b"\x18\x00" + data[ba + 10:])  # 24 bits allocated, 16 stored
    with pytest.raises(ReadError, match=r"14_001.dcm: damaged DICOM file: element \(7FE0,0010\) .* holds \d+ bytes of "
                                        r"pixel data, and one frame of \d+ × \d+ at 24 bits needs \d+"):
        check_dicom_file(victim)
    victim.write_bytes(data[:bs + 8] + b"\x10\x08" + data[bs + 10:])  # 2064 bits stored of 16
    with pytest.raises(ReadError, match=r"element \(0028,0101\) at byte \d+: BitsStored is 2064, not 1…16"):
        read_image(tmp_path / "ct")
    victim.write_bytes(data[:ba + 8] + b"\x0c\x00" + data[ba + 10:])  # 12 bits allocated: no standard size
    with pytest.raises(ReadError, match="BitsAllocated is 12, not 1 or a multiple of 8"):
        check_dicom_file(victim)
