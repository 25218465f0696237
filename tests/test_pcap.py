"""pcap/pcapng reading and pcap writing: formats, framing, skipped traffic, broken files."""

from __future__ import annotations

import struct
from pathlib import Path

import dpkt
import numpy as np
import pytest
import velodyne_decoder as vd
from pcapng import FileWriter, blocks

from twin.lidar.pcap import (
    LINKTYPE_LINUX_SLL,
    CaptureFormatError,
    PcapWriter,
    ipv4_udp_frame,
    read_pcap,
)


@pytest.fixture(scope="module")
def real_records(sample_pcap):
    reader = read_pcap(sample_pcap)
    records = list(reader)
    return records, reader.stats


def test_reads_the_real_capture(real_records, sample_pcap):
    records, stats = real_records
    assert len(records) == 84 and stats.records == 84 and stats.udp == 84
    assert stats.n_skipped == 0 and not stats.truncated_file
    assert stats.format == "pcap" and not stats.nanosecond and stats.byte_order == "<"
    r = records[0]
    assert (r.src_ip, r.dst_ip, r.src_port, r.dst_port) == (
        "192.168.1.200", "255.255.255.255", 2368, 2368)
    assert all(len(x.payload) == 1206 for x in records)
    assert r.timestamp == pytest.approx(1525347606.36204, abs=1e-6)
    # The same payloads and times as an independent reader (dpkt) finds.
    with open(sample_pcap, "rb") as f:
        ref = [(ts, bytes(dpkt.ethernet.Ethernet(buf).data.data.data))
               for ts, buf in dpkt.pcap.Reader(f)]
    assert [x.payload for x in records] == [p for _, p in ref]
    assert np.allclose([x.timestamp for x in records], [t for t, _ in ref], atol=1e-6)


@pytest.mark.parametrize("nanosecond", [False, True])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_write_read_round_trip(tmp_path, real_records, nanosecond, byte_order):
    records, _ = real_records
    path = tmp_path / "out.pcap"
    t0 = 1_700_000_000.123456789
    with PcapWriter(path, nanosecond=nanosecond, byte_order=byte_order) as w:
        for i, r in enumerate(records):
            w.write_udp(r.payload, t0 + i * 1.327e-3)
    reader = read_pcap(path)
    back = list(reader)
    assert reader.stats.nanosecond == nanosecond and reader.stats.byte_order == byte_order
    assert [b.payload for b in back] == [r.payload for r in records]
    assert (back[0].src_ip, back[0].dst_ip, back[0].dst_port) == (
        "192.168.1.201", "255.255.255.255", 2368)
    tol = 1e-6 if nanosecond else 1e-6 + 1e-7  # float64 at 1.7e9 s resolves ~0.24 us
    assert np.allclose([b.timestamp for b in back], t0 + np.arange(84) * 1.327e-3, atol=tol,
                       rtol=0)


def test_written_file_reads_in_dpkt_and_velodyne_decoder(tmp_path, real_records, sample_pcap):
    records, _ = real_records
    path = tmp_path / "copy.pcap"
    with PcapWriter(path) as w:
        for r in records:
            w.write_udp(r.payload, r.timestamp)
    with open(path, "rb") as f:
        frames = list(dpkt.pcap.Reader(f))
    ip = dpkt.ethernet.Ethernet(frames[0][1]).data
    assert isinstance(ip.data, dpkt.udp.UDP) and ip.sum == dpkt.ip.IP(bytes(ip)).sum
    # Recompute the header checksum independently: a valid header sums to 0xFFFF.
    words = struct.unpack("!10H", bytes(ip)[:20])
    total = sum(words)
    assert (total & 0xFFFF) + (total >> 16) == 0xFFFF
    cfg = vd.Config(model=vd.Model.VLP16, cut_angle=0.0)
    ours = [len(p) for _, p in vd.read_pcap(path, cfg)]
    theirs = [len(p) for _, p in vd.read_pcap(sample_pcap, vd.Config(model=vd.Model.VLP16,
                                                                    cut_angle=0.0))]
    assert ours == theirs == [10149, 21481]


def _pcap_with(tmp_path: Path, frames: list[tuple[bytes, int]], link: int = 1) -> Path:
    """A little-endian us pcap of raw frames: (frame, original length)."""
    path = tmp_path / "mixed.pcap"
    with open(path, "wb") as f:
        f.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, link))
        for i, (frame, orig) in enumerate(frames):
            f.write(struct.pack("<IIII", 1000 + i, 0, len(frame), orig))
            f.write(frame)
    return path


def test_non_vlp_traffic_and_fragments_are_skipped_and_counted(tmp_path):
    vlp = ipv4_udp_frame(bytes(1206), 2368)
    pos = ipv4_udp_frame(bytes(512), 8308)
    dns = ipv4_udp_frame(b"x" * 40, 53)
    frag1 = ipv4_udp_frame(bytes(1206), 2368, more_fragments=True)
    frag2 = ipv4_udp_frame(bytes(100), 2368, fragment_offset_bytes=1480)
    tcp = bytearray(ipv4_udp_frame(bytes(60), 2368))
    tcp[14 + 9] = 6  # protocol: TCP
    arp = b"\xff" * 6 + b"\x00" * 6 + b"\x08\x06" + bytes(28)
    ipv6 = b"\xff" * 6 + b"\x00" * 6 + b"\x86\xdd" + bytes(60)
    vlan = vlp[:12] + b"\x81\x00\x00\x05" + vlp[12:]
    cut = vlp[:200]
    frames = [(vlp, len(vlp)), (pos, len(pos)), (dns, len(dns)), (frag1, len(frag1)),
              (frag2, len(frag2)), (bytes(tcp), len(tcp)), (arp, len(arp)), (ipv6, len(ipv6)),
              (vlan, len(vlan)), (cut, len(vlp))]
    reader = read_pcap(_pcap_with(tmp_path, frames))
    got = list(reader)
    assert [(r.dst_port, len(r.payload)) for r in got] == [(2368, 1206), (8308, 512),
                                                           (2368, 1206)]
    assert reader.stats.records == 10 and reader.stats.udp == 3
    assert dict(reader.stats.skipped) == {"other_port": 1, "fragment": 2, "not_udp": 1,
                                          "not_ipv4": 2, "truncated": 1}
    # ports=None yields every whole UDP datagram.
    assert len(list(read_pcap(reader.path, ports=None))) == 4


def test_linux_cooked_capture(tmp_path):
    vlp = ipv4_udp_frame(bytes(range(256)) * 4 + bytes(182), 2368)
    sll = struct.pack("!HHH8sH", 0, 1, 6, b"\x60\x76\x88\x00\x00\x01\x00\x00", 0x0800)
    path = _pcap_with(tmp_path, [(sll + vlp[14:], len(sll) + len(vlp) - 14)],
                      link=LINKTYPE_LINUX_SLL)
    got = list(read_pcap(path))
    assert len(got) == 1 and got[0].payload == bytes(range(256)) * 4 + bytes(182)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # python-pcapng writing its options
def test_pcapng_is_read(tmp_path, real_records):
    records, _ = real_records
    shb = blocks.SectionHeader(options={"shb_userappl": "aimbench tests"})
    shb.new_member(blocks.InterfaceDescription, link_type=1, options={"if_tsresol": b"\x06"})
    path = tmp_path / "cap.pcapng"
    with open(path, "wb") as f:
        w = FileWriter(f, shb)
        for r in records[:20]:
            epb = shb.new_member(blocks.EnhancedPacket)
            epb.interface_id = 0
            epb.timestamp_high, epb.timestamp_low = divmod(round(r.timestamp * 1e6), 2**32)
            epb.packet_data = ipv4_udp_frame(r.payload)
            w.write_block(epb)
    reader = read_pcap(path)
    got = list(reader)
    assert reader.stats.format == "pcapng"
    assert [g.payload for g in got] == [r.payload for r in records[:20]]
    assert np.allclose([g.timestamp for g in got], [r.timestamp for r in records[:20]],
                       atol=2e-6)


def test_broken_files_raise_one_clear_error(tmp_path, sample_pcap):
    with pytest.raises(CaptureFormatError, match="no such file"):
        read_pcap(tmp_path / "missing.pcap")
    with pytest.raises(CaptureFormatError, match="is a directory"):
        read_pcap(tmp_path)
    empty = tmp_path / "empty.pcap"
    empty.write_bytes(b"")
    with pytest.raises(CaptureFormatError, match="not a pcap"):
        read_pcap(empty)
    text = tmp_path / "notes.pcap"
    text.write_text("these are not packets, but they are long enough to have a header\n")
    with pytest.raises(CaptureFormatError, match="not a pcap or pcapng file"):
        read_pcap(text)
    short = tmp_path / "short.pcap"
    short.write_bytes(sample_pcap.read_bytes()[:12])
    with pytest.raises(CaptureFormatError, match="truncated"):
        read_pcap(short)


def test_file_cut_mid_record_reads_what_is_there(tmp_path, sample_pcap):
    data = sample_pcap.read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(data[: 24 + 10 * (16 + 1248) + 700])  # 10 whole records, then half of one
    reader = read_pcap(cut)
    got = list(reader)
    assert len(got) == 10
    assert reader.stats.truncated_file and reader.stats.skipped["truncated"] == 1
