"""Unit tests of the ppm package without udp-ingress: the JSON of each form,
numbering, signing (the README's test vector), key files, input checks and
status queries against a stand-in server. Run from tools/python:
``python3 -m unittest discover -s tests`` (tests/tests/python.rs runs them,
and the package against the real binaries)."""

import json
import os
import socket
import tempfile
import threading
import time
import unittest

import ppm

README_KEY = bytes(range(32))
README_MSG = '{"ch":[1500,1500,1000,1500],"seq":1,"to":"rover"}'
README_MAC = "19eef9dbcc55a46bd2faaba57d00dc42b04194b7b57493491f68d3032314e1fc"
KEY_HEX = "8f2a55e0c1d94b7e3a6f0b1c2d3e4f5061728394a5b6c7d8e9f0a1b2c3d4e5f6"


class Receiver:
    """A UDP socket on 127.0.0.1 standing in for udp-ingress."""

    def __init__(self, host: str = "127.0.0.1") -> None:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.socket = socket.socket(family, socket.SOCK_DGRAM)
        self.socket.bind((host, 0))
        self.socket.settimeout(2)
        port = self.socket.getsockname()[1]
        self.target = f"[{host}]:{port}" if family == socket.AF_INET6 else f"{host}:{port}"

    def take(self) -> bytes:
        return self.socket.recvfrom(65_536)[0]

    def nothing_pending(self) -> bool:
        self.socket.settimeout(0.05)
        try:
            self.socket.recvfrom(65_536)
            return False
        except socket.timeout:
            return True
        finally:
            self.socket.settimeout(2)

    def close(self) -> None:
        self.socket.close()


class Forms(unittest.TestCase):
    def setUp(self) -> None:
        self.rx = Receiver()
        self.addCleanup(self.rx.close)

    def test_unnumbered_forms(self) -> None:
        with ppm.Sender(self.rx.target, seq=False) as s:
            self.assertEqual(s.send([1000, 1200.5]), b"[1000,1200.5]")
            self.assertEqual(self.rx.take(), b"[1000,1200.5]")
            s.send((1500,))
            self.assertEqual(self.rx.take(), b"[1500]")
            s.send(ail=1600, aux1=1800)
            self.assertEqual(json.loads(self.rx.take()), {"ail": 1600, "aux1": 1800})
            s.send_norm(ail=0.2, thr=-1)
            self.assertEqual(json.loads(self.rx.take()), {"norm": {"ail": 0.2, "thr": -1}})
            s.send_units(ele=-2.5)
            self.assertEqual(json.loads(self.rx.take()), {"units": {"ele": -2.5}})
            self.assertIsNone(s.last_seq)

    def test_numbered_from_the_time_in_microseconds(self) -> None:
        s = ppm.Sender(self.rx.target)
        self.addCleanup(s.close)
        before = time.time_ns() // 1000
        s.send([1100, 1200])
        first = json.loads(self.rx.take())
        self.assertEqual(first["ch"], [1100, 1200])
        self.assertGreaterEqual(first["seq"], before)
        self.assertLess(first["seq"], before + 60_000_000)
        seqs = [first["seq"]]
        s.send(thr=1200)
        d = json.loads(self.rx.take())
        self.assertEqual(set(d), {"thr", "seq"})
        seqs.append(d["seq"])
        s.send_norm(ail=0)
        d = json.loads(self.rx.take())
        self.assertEqual(set(d), {"norm", "seq"})
        seqs.append(d["seq"])
        s.send_units(ail=1)
        d = json.loads(self.rx.take())
        self.assertEqual(set(d), {"units", "seq"})
        seqs.append(d["seq"])
        self.assertEqual(seqs, sorted(set(seqs)), "strictly growing")
        self.assertEqual(s.last_seq, seqs[-1])
        # A sender started later (a restarted groundstation) starts above.
        with ppm.Sender(self.rx.target) as again:
            again.send([1500])
            self.assertGreater(json.loads(self.rx.take())["seq"], seqs[-1])

    def test_bad_input_is_refused_before_sending(self) -> None:
        s = ppm.Sender(self.rx.target)
        self.addCleanup(s.close)
        cases = [
            (lambda: s.send([1500], ail=1500), "not both"),
            (lambda: s.send(), "no channel"),
            (lambda: s.send([]), "0 values"),
            (lambda: s.send([1500] * 17), "17 values"),
            (lambda: s.send("1500"), "list of microseconds"),
            (lambda: s.send(1500), "list of microseconds"),
            (lambda: s.send([1500, "1500"]), "channel 2 is '1500', not a number"),
            (lambda: s.send([None]), "not a number"),
            (lambda: s.send([True]), "not a number"),
            (lambda: s.send([float("nan")]), "channel 1 is nan, not a finite number"),
            (lambda: s.send(thr=float("inf")), "channel `thr` is inf"),
            (lambda: s.send([3000]), "3000 us is outside 500..2500"),
            (lambda: s.send(ail=499.9), "outside 500..2500"),
            (lambda: s.send(yaw=1500), "no channel `yaw`"),
            (lambda: s.send(aux13=1500), "no channel `aux13`"),
            (lambda: s.send(ail=1500, seq=5), "`seq` is not a channel"),
            (lambda: s.send_norm(), "no channel"),
            (lambda: s.send_norm(ail=float("-inf")), "norm `ail` is -inf"),
            (lambda: s.send_norm(ail="0.2"), "not a number"),
            (lambda: s.send_units(ail=float("nan")), "units `ail` is nan"),
            (lambda: s.send_units(ch=3), "no channel `ch`"),
        ]
        for call, words in cases:
            with self.subTest(words=words):
                with self.assertRaises(ValueError) as e:
                    call()
                self.assertIn(words, str(e.exception))
        self.assertTrue(self.rx.nothing_pending(), "nothing was sent")
        self.assertIsNone(s.last_seq, "no seq was used")

    def test_targets(self) -> None:
        self.assertEqual(ppm.parse_target("[::1]:5005"), ("::1", 5005))
        self.assertEqual(ppm.parse_target("localhost:1"), ("localhost", 1))
        for bad in ["5005", "host:", ":5005", "host:0", "host:70000", "::1:5005", "h:x"]:
            with self.subTest(bad=bad), self.assertRaises(ValueError):
                ppm.Sender(bad)

    def test_ipv6(self) -> None:
        try:
            rx = Receiver("::1")
        except OSError:
            self.skipTest("no IPv6 loopback")
        self.addCleanup(rx.close)
        with ppm.Sender(rx.target, seq=False) as s:
            s.send([1500])
            self.assertEqual(rx.take(), b"[1500]")


class Signing(unittest.TestCase):
    def test_readme_vector(self) -> None:
        self.assertEqual(ppm.sign(README_KEY, README_MSG), README_MAC)
        self.assertEqual(
            ppm.envelope(README_KEY, README_MSG),
            '{"msg":"{\\"ch\\":[1500,1500,1000,1500],\\"seq\\":1,\\"to\\":\\"rover\\"}","mac":"'
            + README_MAC
            + '"}',
        )

    def setUp(self) -> None:
        self.dir = tempfile.TemporaryDirectory()
        self.addCleanup(self.dir.cleanup)

    def key_file(self, text: str, mode: int = 0o600) -> str:
        path = os.path.join(self.dir.name, f"{len(os.listdir(self.dir.name))}.key")
        with open(path, "w") as f:
            f.write(text)
        os.chmod(path, mode)
        return path

    def test_signed_datagrams(self) -> None:
        rx = Receiver()
        self.addCleanup(rx.close)
        path = self.key_file(f"  {KEY_HEX.upper()}\n")
        with ppm.Sender(rx.target, key_file=path, name="rover") as s:
            s.send(ail=1500)
            d = json.loads(rx.take())
            self.assertEqual(set(d), {"msg", "mac"})
            self.assertEqual(d["mac"], ppm.sign(bytes.fromhex(KEY_HEX), d["msg"]))
            cmd = json.loads(d["msg"])
            self.assertEqual(cmd, {"ail": 1500, "seq": s.last_seq, "to": "rover"})
            s.send([1100])
            cmd = json.loads(json.loads(rx.take())["msg"])
            self.assertEqual(cmd, {"ch": [1100], "seq": s.last_seq, "to": "rover"})
            self.assertIn("name='rover'", repr(s))
        with self.assertRaisesRegex(ValueError, "seq=True"):
            ppm.Sender(rx.target, key_file=path, seq=False, name="rover")
        # The name is what binds a signed command to its vehicle: required.
        with self.assertRaisesRegex(ValueError, "a key needs name="):
            ppm.Sender(rx.target, key_file=path)
        self.assertTrue(rx.nothing_pending())

    def test_output_names(self) -> None:
        rx = Receiver()
        self.addCleanup(rx.close)
        # Unsigned commands may name their output too (udp-ingress then checks it).
        with ppm.Sender(rx.target, seq=False, name="plane-1") as s:
            s.send([1500])
            self.assertEqual(json.loads(rx.take()), {"ch": [1500], "to": "plane-1"})
            s.send_norm(thr=-1)
            self.assertEqual(json.loads(rx.take()), {"norm": {"thr": -1}, "to": "plane-1"})
            with self.assertRaisesRegex(ValueError, "`to` is not a channel"):
                s.send(to=1500)
        for bad in ["", "a b", "x" * 65, 5, "rövér"]:
            with self.subTest(name=bad):
                with self.assertRaisesRegex(ValueError, "no output name"):
                    ppm.Sender(rx.target, name=bad)
        self.assertTrue(rx.nothing_pending())

    def test_key_files_refused_like_udp_ingress(self) -> None:
        good = self.key_file(KEY_HEX)
        self.assertEqual(ppm.load_key(good), bytes.fromhex(KEY_HEX))
        cases = [
            (self.key_file(KEY_HEX, 0o644), "(mode 0644): run `chmod 600"),
            (self.key_file(KEY_HEX, 0o620), "accessible by group or others"),
            (self.key_file(KEY_HEX[:62]), "found 62 characters"),
            (self.key_file(KEY_HEX.replace("a", "g")), "not hex"),
            (self.key_file(KEY_HEX[:32] + "  " + KEY_HEX[34:]), "not hex"),
            (self.key_file("0" * 5000), "never larger than 4096"),
            (os.path.join(os.path.dirname(good), "missing"), "cannot read auth key file"),
            ("/dev/zero", "a character device, not a regular file"),
            ("/", "a directory"),
        ]
        fifo = os.path.join(os.path.dirname(good), "fifo")
        os.mkfifo(fifo, 0o600)
        cases.append((fifo, "a FIFO (named pipe), not a regular file"))
        for path, words in cases:
            with self.subTest(path=path):
                with self.assertRaises(ppm.KeyFileError) as e:
                    ppm.Sender("127.0.0.1:9", key_file=path, name="rover")
                self.assertIn(words, str(e.exception))
                self.assertIn(path, str(e.exception))


class Status(unittest.TestCase):
    def serve(self, answers: list, query: bytes = b'{"get":"status"}') -> tuple:
        """A stand-in ingress answering each `query` with the next of `answers`;
        returns its target and the list of query sizes it got."""
        rx = Receiver()
        self.addCleanup(rx.close)
        sizes = []

        def run() -> None:
            for a in answers:
                q, peer = rx.socket.recvfrom(65_536)
                sizes.append(len(q))
                self.assertEqual(q.rstrip(b" "), query)
                rx.socket.sendto(a, peer)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        self.addCleanup(t.join, 5)
        return rx.target, sizes

    def test_padded_and_retried_once_at_pad_to(self) -> None:
        full = b'{"datagrams": {"received": 3}, "status_short": 0}'
        target, sizes = self.serve([b'{"pad_to":1500}', full])
        with ppm.Sender(target) as s:
            self.assertEqual(s.status(), json.loads(full))
        self.assertEqual(sizes, [1400, 1500])

    def test_telemetry_is_the_member_alone(self) -> None:
        member = {"state": "receiving", "battery": {"voltage_v": 16.8}}
        answer = json.dumps({"name": "plane", "telemetry": member}).encode()
        target, sizes = self.serve([b'{"pad_to":1500}', answer], b'{"get":"telemetry"}')
        with ppm.Sender(target) as s:
            self.assertEqual(s.telemetry(), member)
        self.assertEqual(sizes, [1400, 1500])
        target, _ = self.serve([b'{"name": "plane", "telemetry": null}'], b'{"get":"telemetry"}')
        with ppm.Sender(target) as s:
            self.assertIsNone(s.telemetry())

    def test_answer_without_pad_to(self) -> None:
        target, sizes = self.serve([b'{"datagrams": {}}'])
        with ppm.Sender(target) as s:
            self.assertEqual(s.status(), {"datagrams": {}})
        self.assertEqual(sizes, [1400])

    def test_still_too_short_and_not_json(self) -> None:
        target, _ = self.serve([b'{"pad_to":1500}', b'{"pad_to":1600}'])
        with ppm.Sender(target) as s, self.assertRaisesRegex(ppm.PpmError, "still answers"):
            s.status()
        target, _ = self.serve([b"[1, 2]"])
        with ppm.Sender(target) as s, self.assertRaisesRegex(ppm.PpmError, "not a JSON object"):
            s.status()

    def test_timeout(self) -> None:
        rx = Receiver()  # listens, never answers
        self.addCleanup(rx.close)
        with ppm.Sender(rx.target) as s:
            t = time.monotonic()
            with self.assertRaises(ppm.StatusTimeout) as e:
                s.status(timeout=0.2)
            self.assertLess(time.monotonic() - t, 2)
        self.assertIn("no status reply from", str(e.exception))
        self.assertIsInstance(e.exception, TimeoutError)
        with ppm.Sender(rx.target) as s, self.assertRaises(ValueError):
            s.status(timeout=0)

    def test_nothing_listening(self) -> None:
        rx = Receiver()
        target = rx.target
        rx.close()
        # Refused (port unreachable): the documented StatusTimeout, saying why.
        with ppm.Sender(target) as s, self.assertRaises(ppm.StatusTimeout) as e:
            s.status(timeout=2)
        self.assertRegex(str(e.exception), f"^no status reply from {target}: it refused the query")
        self.assertIn("nothing listens there", str(e.exception))
        self.assertIsInstance(e.exception, TimeoutError)


if __name__ == "__main__":
    unittest.main()
