"""Run ROS 2 processes for tests and benchmarks on loopback only (DESIGN.md section 4).

Every process that starts rclpy gets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a
``ROS_DOMAIN_ID`` of its own (1..100, from the pid and a per-process counter). When ``unshare -n``
works (detected once), the whole exchange runs in a fresh network namespace with only ``lo`` up.
Processes in different network namespaces cannot discover each other, so the node under test and
the publishing/listening side share ONE namespace: :func:`run_driver` starts a driver process
inside the namespace, and the driver starts the node as its child (:meth:`RosSession.start_estimator`).

Two ways to drive a test:

* :func:`run_scenario` — a declarative script (publish these messages, spin, set parameters, call a
  service, mark the time); the driver returns everything it received as JSON-able dicts.
* :func:`run_driver` with ``"module:function"`` — the function runs inside the namespace with an
  argument dict and returns a JSON-able result (the benchmark uses this).

The test process itself never initialises rclpy.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
_counter = itertools.count()


class DriverError(RuntimeError):
    """The driver process failed; the message holds its output."""


# --------------------------------------------------------------------------- isolation


@functools.cache
def unshare_works() -> bool:
    """Whether ``unshare -n`` (a fresh network namespace with lo up) is permitted here; checked once."""
    try:
        result = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return False
    return result.returncode == 0


def domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..100, different for each call in this process (for 100 calls)."""
    return 1 + (os.getpid() * 37 + next(_counter)) % 100


def ros_env(domain: int, extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment for a process that starts rclpy: loopback discovery, its own domain."""
    env = dict(os.environ)
    for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE",
                "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_DISCOVERY_SERVER"):
        env.pop(key, None)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain)
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), str(HERE), env.get("PYTHONPATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    # a ROS_HOME of its own: the node keeps its learned state there (persistence.file), and one test's
    # state must not become the next test's starting point
    env["ROS_HOME"] = tempfile.mkdtemp(prefix="ros_home_")
    env.update(extra or {})
    return env


def isolated(command: list[str]) -> list[str]:
    """``command`` wrapped to run in a fresh network namespace with lo up, when that is permitted."""
    if not unshare_works():
        return command
    return ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh", *command]


def estimator_command(*ros_args: str, options: Iterable[str] = ()) -> list[str]:
    """The installed ``estimator`` next to this interpreter, else ``python -m transplanter_ident.ros.main``.

    ``options`` (e.g. ``--executor single``) go before ``--ros-args``.
    """
    script = Path(sys.executable).parent / "estimator"
    base = [str(script)] if script.is_file() else [sys.executable, "-m", "transplanter_ident.ros.main"]
    base = [*base, *options]
    return [*base, "--ros-args", *ros_args] if ros_args else base


def run_driver(target: str, args: dict[str, Any], timeout: float, extra_env: dict[str, str] | None = None) -> Any:
    """Run ``target`` ("module:function", module in test/ or importable) isolated; return its result.

    The driver gets its own ROS_DOMAIN_ID and, when permitted, its own network namespace.
    """
    with tempfile.TemporaryDirectory(prefix="ros_driver_") as tmp:
        args_path, out_path = Path(tmp) / "args.json", Path(tmp) / "result.json"
        args_path.write_text(json.dumps({**args, "_tmp": tmp}))
        command = isolated([sys.executable, str(Path(__file__)), target, str(args_path), str(out_path)])
        domain = domain_id()
        try:
            proc = subprocess.run(command, env=ros_env(domain, extra_env), capture_output=True, text=True,
                                  timeout=timeout, cwd=ROOT)
        except subprocess.TimeoutExpired as exc:
            raise DriverError(f"{target} timed out after {timeout} s\nstdout:\n{exc.stdout}\nstderr:\n{exc.stderr}"
                              ) from None
        if proc.returncode != 0 or not out_path.is_file():
            raise DriverError(f"{target} failed (rc {proc.returncode}, domain {domain})\nstdout:\n{proc.stdout[-5000:]}"
                              f"\nstderr:\n{proc.stderr[-10000:]}")
        return json.loads(out_path.read_text())


def run_scenario(spec: dict[str, Any], timeout: float = 120.0) -> dict[str, Any]:
    """Run a declarative scenario (see :func:`scenario`) in an isolated driver; return what it recorded."""
    return run_driver("ros_harness:scenario", spec, timeout)


# --------------------------------------------------------------------------- messages


def message_class(type_name: str) -> type:
    """'geometry_msgs/msg/TwistStamped' (or 'geometry_msgs/TwistStamped') -> the rclpy class."""
    package, _, name = type_name.replace("/msg/", "/").partition("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def build_message(type_name: str, fields: dict[str, Any]) -> Any:
    """A message with dotted-path fields set, e.g. {'header.stamp.sec': 1, 'twist.linear.x': 2.0}."""
    msg = message_class(type_name)()
    for path, value in fields.items():
        *parents, leaf = path.split(".")
        target = msg
        for part in parents:
            target = getattr(target, part)
        setattr(target, leaf, value)
    return msg


def message_to_dict(msg: Any) -> Any:
    """A message as plain JSON-able data (bytes of length one, e.g. a diagnostic level, become ints)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: message_to_dict(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, bytes):
        return msg[0] if len(msg) == 1 else list(msg)
    if isinstance(msg, (str, int, float, bool)) or msg is None:
        return msg
    return [message_to_dict(v) for v in msg]


def stamp_fields(t: float) -> dict[str, int]:
    """header.stamp fields for float seconds (nearest nanosecond)."""
    sec = math.floor(t)
    nanosec = round((t - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return {"header.stamp.sec": int(sec), "header.stamp.nanosec": int(nanosec)}


# --------------------------------------------------------------------------- inside the driver


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the driver dies (no orphaned nodes after a timeout)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class RosSession:
    """An rclpy node on the driver side, plus the estimator process it started."""

    def __init__(self, name: str = "test_driver") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node(name)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.records: dict[str, list[dict[str, Any]]] = {}
        self._subscriptions: dict[str, Any] = {}
        self._publishers: dict[tuple[str, str], Any] = {}
        self.process: subprocess.Popen | None = None
        self.log_path: Path | None = None

    # -- the node under test

    def start_estimator(self, ros_args: Iterable[str], log_path: Path, command: list[str] | None = None,
                        options: Iterable[str] = ()) -> None:
        """Start the estimator (a child process in this namespace); its output goes to ``log_path``."""
        self.log_path = Path(log_path)
        log = self.log_path.open("w")
        self.process = subprocess.Popen(command or estimator_command(*ros_args, options=options), stdout=log, stderr=subprocess.STDOUT,
                                        preexec_fn=_die_with_parent, cwd=ROOT)
        log.close()

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop_estimator(self, timeout: float = 15.0, stop_signal: str = "SIGINT") -> int | None:
        """SIGINT (or ``stop_signal``), then wait; SIGKILL if it hangs. Returns the exit code."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(getattr(signal, stop_signal))
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
        return self.process.returncode

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path and self.log_path.exists() else ""

    # -- topics

    def record(self, key: str, topic: str, type_name: str, depth: int = 10000) -> None:
        """Keep every message on ``topic`` as {'t': monotonic receive time, 'msg': dict}."""
        store = self.records.setdefault(key, [])
        self.subscribe(key, topic, type_name,
                       lambda msg: store.append({"t": time.monotonic(), "msg": message_to_dict(msg)}), depth)

    def subscribe(self, key: str, topic: str, type_name: str, callback: Callable[[Any], None],
                  depth: int = 1000) -> None:
        """A reliable subscription with a callback of one's own (counted by :meth:`wait_matched`)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self._subscriptions[key] = self.node.create_subscription(message_class(type_name), topic, callback, qos)

    def publisher(self, topic: str, type_name: str, depth: int = 1000) -> Any:
        key = (topic, type_name)
        if key not in self._publishers:
            self._publishers[key] = self.node.create_publisher(message_class(type_name), topic, depth)
        return self._publishers[key]

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0.0:
                return
            self.executor.spin_once(timeout_sec=left)

    def spin_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            left = deadline - time.monotonic()
            if left <= 0.0:
                return predicate()
            self.executor.spin_once(timeout_sec=min(left, 0.05))
        return True

    def wait_matched(self, timeout: float = 30.0, settle: float = 1.5) -> None:
        """Wait until every publisher has a subscriber and every recorder a publisher (the node is up)."""
        def matched() -> bool:
            return (all(p.get_subscription_count() > 0 for p in self._publishers.values())
                    and all(s.get_publisher_count() > 0 for s in self._subscriptions.values()))

        if not self.spin_until(matched, timeout):
            raise RuntimeError(f"endpoints not matched within {timeout} s (node alive: {self.alive()})\n"
                               + self.log_text())
        # discovery completes on each side separately: give the node's readers time to match our writers (its
        # inputs are best effort: a sample sent before then is lost; 0.5 s lost the first 0.2 s of a drive once
        # under the suite's load, test_single_antenna_node in session 32's CI)
        self.spin_for(settle)

    # -- services

    def _call(self, srv_type: type, name: str, request: Any, timeout: float = 10.0) -> Any:
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise RuntimeError(f"service {name} not available")
            future = client.call_async(request)
            self.spin_until(future.done, timeout)
            if not future.done():
                raise RuntimeError(f"service {name} did not answer within {timeout} s")
            return future.result()
        finally:
            self.node.destroy_client(client)

    def set_parameters(self, node_name: str, values: dict[str, Any]) -> list[dict[str, Any]]:
        """Set parameters through the node's ``set_parameters`` service; one result per parameter."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        response = self._call(SetParameters, f"{node_name}/set_parameters", request)
        return [{"successful": r.successful, "reason": r.reason} for r in response.results]

    def get_parameters(self, node_name: str, names: list[str]) -> dict[str, Any]:
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        response = self._call(GetParameters, f"{node_name}/get_parameters", GetParameters.Request(names=names))
        return {name: _jsonable(parameter_value_to_python(v)) for name, v in zip(names, response.values, strict=True)}

    def trigger(self, name: str) -> dict[str, Any]:
        from std_srvs.srv import Trigger

        response = self._call(Trigger, name, Trigger.Request())
        return {"success": response.success, "message": response.message}

    def close(self) -> None:
        self.stop_estimator()
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def _jsonable(value: Any) -> Any:
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return [_jsonable(v) for v in value]


def scenario(spec: dict[str, Any]) -> dict[str, Any]:
    """Run a declarative scenario inside the driver (target ``ros_harness:scenario``).

    spec keys:
      estimator_args: ROS arguments of the node (after --ros-args); node name 'estimator'
      estimator_options: options of the node before --ros-args (e.g. ["--executor", "single"])
      record: {key: [topic, type]} to record
      publish_types: [[topic, type], ...] publishers to create up front (matched before the steps)
      steps: a list of one-key dicts, in order:
        {"publish": [{"topic", "type", "fields", "at"?}, ...], "pace": s} -- each message, then spin
            ``pace`` seconds; with "at" (s from the step's start) messages go out on that schedule
        {"spin": s}
        {"wait_for": [key, count, timeout]}      spin until ``count`` messages are recorded; one that times
            out is listed in results["timed_out"] (step index, key, count, recorded), and with the spec's
            "stop_at_timeout" true the steps end there (a lost message would time every later wait out)
        {"mark": name}                           monotonic time and record counts
        {"set_parameters": {name: value}, "as": name, "node"?: "/estimator"}
        {"get_parameters": [names], "as": name, "node"?: "/estimator"}
        {"trigger": service, "as": name}
    Returns {"records", "marks", "results", "alive", "returncode", "log"}.
    """
    session = RosSession()
    marks: dict[str, Any] = {}
    results: dict[str, Any] = {}
    alive_at_end = False
    try:
        for key, (topic, type_name) in spec.get("record", {}).items():
            session.record(key, topic, type_name)
        for topic, type_name in spec.get("publish_types", []):
            session.publisher(topic, type_name)
        session.start_estimator(spec.get("estimator_args", []), Path(spec["_tmp"]) / "estimator.log",
                                options=spec.get("estimator_options", []))
        session.wait_matched(spec.get("match_timeout", 30.0))
        for index, step in enumerate(spec["steps"]):
            met = _run_step(session, step, marks, results)
            if not met:
                key, count, _ = step["wait_for"]
                results.setdefault("timed_out", []).append([index, key, count, len(session.records.get(key, []))])
                if spec.get("stop_at_timeout", False):
                    break
        alive_at_end = session.alive()
    finally:
        returncode = session.stop_estimator(stop_signal=spec.get("stop_signal", "SIGINT"))
        records = session.records
        log = session.log_text()
        session.close()
    return {"records": records, "marks": marks, "results": results, "alive": alive_at_end,
            "returncode": returncode, "log": log}


def _run_step(session: RosSession, step: dict[str, Any], marks: dict[str, Any], results: dict[str, Any]) -> bool:
    """Run one scenario step; False when it was a wait_for that timed out."""
    if "publish" in step:
        pace = float(step.get("pace", 0.002))
        start = time.monotonic()
        for item in step["publish"]:
            if "at" in item:
                left = start + float(item["at"]) - time.monotonic()
                if left > 0.0:
                    session.spin_for(left)
            session.publisher(item["topic"], item["type"]).publish(build_message(item["type"], item["fields"]))
            if "at" not in item:
                session.spin_for(pace)
    elif "spin" in step:
        session.spin_for(float(step["spin"]))
    elif "wait_for" in step:
        key, count, timeout = step["wait_for"]
        return session.spin_until(lambda: len(session.records.get(key, [])) >= count, float(timeout))
    elif "mark" in step:
        marks[step["mark"]] = {"t": time.monotonic(), "counts": {k: len(v) for k, v in session.records.items()},
                               "alive": session.alive()}
    elif "set_parameters" in step:
        results[step["as"]] = session.set_parameters(step.get("node", "/estimator"), step["set_parameters"])
    elif "get_parameters" in step:
        results[step["as"]] = session.get_parameters(step.get("node", "/estimator"), step["get_parameters"])
    elif "trigger" in step:
        results[step["as"]] = session.trigger(step["trigger"])
    else:
        raise ValueError(f"unknown scenario step {step}")
    return True


def _driver_main(argv: list[str]) -> int:
    target, args_path, out_path = argv
    module_name, _, function_name = target.partition(":")
    for path in (str(HERE), str(ROOT)):
        if path not in sys.path:
            sys.path.insert(0, path)
    module = sys.modules[__name__] if module_name in ("ros_harness", "__main__") else importlib.import_module(
        module_name)
    result = getattr(module, function_name)(json.loads(Path(args_path).read_text()))
    Path(out_path).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(_driver_main(sys.argv[1:]))
