"""Config dataclasses as node parameters (in-process rclpy node, no other process)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from ros_harness import reserve_domain_id

from der_ros.configuration import ConfigError, param, unflatten_names
from der_ros.nodes.params import ConfigParameters, flat_parameters, flat_specs


@dataclass
class Inner:
    """Nested section."""

    scale: float = param(2.0, "a scale", low=0.0, low_inclusive=False)
    kind: str = param("a", "a kind", choices=("a", "b"))


@dataclass
class Outer:
    """Top section."""

    lam: float = param(0.5, "the lambda of eq. 3", low=0.0, high=1.0)
    count: int = param(4, "a count", low=1)
    lo: float = param(0.1, "lower", low=0.0)
    hi: float = param(0.9, "upper", low=0.0)
    flag: bool = param(False, "a flag")
    sizes: list[int] = param(default_factory=lambda: [8, 8], help="sizes")
    inner: Inner = param(default_factory=Inner, help="nested")
    path: str | None = param(None, "optional path")

    def check(self) -> None:
        if self.lo > self.hi:
            raise ConfigError(f"lo = {self.lo!r}, expected <= hi ({self.hi!r})")


def test_flatten_roundtrip_without_ros():
    flat = flat_parameters("sec", Outer())
    assert flat["sec.inner.scale"] == 2.0 and flat["sec.sizes"] == [8, 8] and flat["sec.path"] is None
    assert set(flat) == set(flat_specs(Outer, "sec"))
    assert unflatten_names(flat, "sec")["inner"] == {"scale": 2.0, "kind": "a"}
    assert set(flat_parameters("", Outer())) >= {"lam", "inner.kind"}


@pytest.fixture
def node():
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    lease = reserve_domain_id()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=lease.domain_id)
    n = Node("params_test", context=ctx)
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.shutdown(context=ctx)
        lease.release()


def test_declares_descriptors_and_reads_back(node):
    from rcl_interfaces.msg import ParameterType

    bound = ConfigParameters(node, {"sec": Outer(count=7), "": Inner()}, mutable={"sec.lam", "sec.lo", "sec.hi"})
    assert bound.get("sec") == Outer(count=7)
    assert bound.get("") == Inner()
    d = node.describe_parameter("sec.lam")
    assert d.description == "the lambda of eq. 3" and not d.read_only
    assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (0.0, 1.0)
    d = node.describe_parameter("sec.count")
    assert d.read_only and d.integer_range[0].from_value == 1 and d.type == ParameterType.PARAMETER_INTEGER
    assert "one of" in node.describe_parameter("kind").additional_constraints
    assert "> 0.0" in node.describe_parameter("sec.inner.scale").additional_constraints
    assert node.describe_parameter("sec.sizes").type == ParameterType.PARAMETER_INTEGER_ARRAY
    assert node.get_parameter("sec.path").value is None
    assert "sec.inner.kind" in bound.names and "scale" in bound.names


def test_rejects_invalid_values_with_reason_and_keeps_old(node):
    from rclpy.parameter import Parameter

    changes = []
    bound = ConfigParameters(
        node, {"sec": Outer()}, mutable={"sec.lam", "sec.lo", "sec.hi"}, on_change=lambda *a: changes.append(a)
    )
    # out of the declared range: refused by the descriptor before our callback
    (res,) = node.set_parameters([Parameter("sec.lam", value=1.5)])
    assert not res.successful and "sec.lam" in res.reason
    # cross-field rule of the dataclass: refused by the validation callback, reason names the field
    (res,) = node.set_parameters([Parameter("sec.lo", value=0.95)])
    assert not res.successful and "lo = 0.95" in res.reason and "hi" in res.reason
    # read-only
    (res,) = node.set_parameters([Parameter("sec.count", value=9)])
    assert not res.successful and "read-only" in res.reason
    # wrong type
    (res,) = node.set_parameters([Parameter("sec.lam", value="high")])
    assert not res.successful
    assert node.get_parameter("sec.lam").value == 0.5 and node.get_parameter("sec.lo").value == 0.1
    assert bound.get("sec") == Outer() and changes == []
    # a valid change is applied and reported
    (res,) = node.set_parameters([Parameter("sec.lam", value=0.25)])
    assert res.successful
    assert bound.get("sec").lam == 0.25
    assert changes == [("sec", bound.get("sec"), ["sec.lam"])]
    # atomic pair that is only valid together
    res = node.set_parameters_atomically([Parameter("sec.hi", value=2.0), Parameter("sec.lo", value=1.5)])
    assert res.successful and bound.get("sec").lo == 1.5


def test_bad_startup_override_raises(node):
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    # what `-p sec.lo:=5.0` on the command line does
    bad = Node("params_test_bad", context=node.context, parameter_overrides=[Parameter("sec.lo", value=5.0)])
    try:
        with pytest.raises(ConfigError, match="lo = 5.0"):
            ConfigParameters(bad, {"sec": Outer()})
    finally:
        bad.destroy_node()


def test_unknown_mutable_name_is_an_error(node):
    with pytest.raises(ValueError, match="sec.nope"):
        ConfigParameters(node, {"sec": Outer()}, mutable={"sec.nope"})

