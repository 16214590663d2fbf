"""``ros2 node list`` and ``ros2 param list|get|set|describe``, printing what ros2cli prints.

Parameters go through each node's standard parameter services
(``<node>/list_parameters``, ``get_parameters``, ``set_parameters``,
``describe_parameters``), so any ROS 2 node answers, not only this project's.
"""

from __future__ import annotations

import argparse
import sys

from .graph import DISCOVERY_SPIN_S, absolute_node_name, all_node_names_known, cli_node, hidden, node_names, spin_for_discovery, wait_for_node

NODE_TIMEOUT_S = 5.0  # no daemon: discovery starts from scratch on every call
SERVICE_TIMEOUT_S = 10.0

TYPE_LABELS = {  # rcl_interfaces/ParameterType -> (ros2 param get label, value field)
    1: ("Boolean value is:", "bool_value"),
    2: ("Integer value is:", "integer_value"),
    3: ("Double value is:", "double_value"),
    4: ("String value is:", "string_value"),
    5: ("Byte values are:", "byte_array_value"),
    6: ("Boolean values are:", "bool_array_value"),
    7: ("Integer values are:", "integer_array_value"),
    8: ("Double values are:", "double_array_value"),
    9: ("String values are:", "string_array_value"),
}
TYPE_NAMES = {0: "not set", 1: "boolean", 2: "integer", 3: "double", 4: "string", 5: "byte array",
              6: "boolean array", 7: "integer array", 8: "double array", 9: "string array"}


# ---------------------------------------------------------------- node
def node_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="ros2 node", description="Various node related sub-commands")
    sub = parser.add_subparsers(dest="verb", metavar="Commands")
    list_p = sub.add_parser("list", help="Output a list of available nodes")
    list_p.add_argument("-a", "--all", action="store_true", help="Display all nodes even hidden ones")
    list_p.add_argument("-c", "--count-nodes", action="store_true", help="Only display the number of nodes discovered")
    list_p.add_argument("--spin-time", type=float, default=DISCOVERY_SPIN_S, help="Seconds to wait for discovery")
    opts = parser.parse_args(args)
    if opts.verb != "list":
        parser.print_help()
        return 2
    with cli_node() as node:
        names = spin_for_discovery(node, opts.spin_time, lambda: node_names(node),
                                   lambda names: all_node_names_known(node, names))
    names = [n for n in names if opts.all or not hidden(n)]
    if opts.count_nodes:
        print(len(names))
    else:
        for name in names:
            print(name)
    return 0


# ---------------------------------------------------------------- param
def param_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="ros2 param", description="Various param related sub-commands")
    sub = parser.add_subparsers(dest="verb", metavar="Commands")
    list_p = sub.add_parser("list", help="Output a list of available parameters")
    list_p.add_argument("node_name", nargs="?", help="Name of the ROS node")
    list_p.add_argument("--param-type", action="store_true", help="Print parameter types with parameter names")
    list_p.add_argument("--spin-time", type=float, default=DISCOVERY_SPIN_S, help="Seconds to wait for discovery")
    get_p = sub.add_parser("get", help="Get parameter")
    get_p.add_argument("node_name", help="Name of the ROS node")
    get_p.add_argument("parameter_name", help="Name of the parameter")
    get_p.add_argument("--hide-type", action="store_true", help="Hide the type information")
    set_p = sub.add_parser("set", help="Set parameter")
    set_p.add_argument("node_name", help="Name of the ROS node")
    set_p.add_argument("params_and_values", nargs="+", metavar="name value",
                       help="Parameter name and value pair(s): name value [name value ...]")
    describe_p = sub.add_parser("describe", help="Show descriptive information about declared parameters")
    describe_p.add_argument("node_name", help="Name of the ROS node")
    describe_p.add_argument("parameter_names", nargs="+", help="Names of the parameters")
    for p in (get_p, set_p, describe_p):
        p.add_argument("--timeout", type=float, default=NODE_TIMEOUT_S,
                       help="Wait for N seconds until node becomes available (default %(default)s sec)")
    opts = parser.parse_args(args)
    if opts.verb is None:
        parser.print_help()
        return 2
    if opts.verb == "set" and len(opts.params_and_values) % 2:
        print("Parameters must be provided as name/value pairs: name value [name value ...]. "
              f"Got {len(opts.params_and_values)} argument(s).", file=sys.stderr)
        return 1
    with cli_node() as node:
        if opts.verb == "list":
            return _list(node, opts)
        target = absolute_node_name(opts.node_name)
        if not wait_for_node(node, target, opts.timeout):
            print("Node not found", file=sys.stderr)
            return 1
        return {"get": _get, "set": _set, "describe": _describe}[opts.verb](node, target, opts)


def _call(node, target: str, service: str, request):
    """Call ``target/service``; the response, or None (with the reason on stderr)."""
    import rclpy

    client = node.create_client(_service_type(service), f"{target}/{service}")
    try:
        if not client.wait_for_service(timeout_sec=SERVICE_TIMEOUT_S):
            print(f"Service {target}/{service} is not available", file=sys.stderr)
            return None
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=SERVICE_TIMEOUT_S)
        if not future.done():
            print(f"No answer from {target}/{service}", file=sys.stderr)
            return None
        return future.result()
    finally:
        node.destroy_client(client)


def _service_type(service: str):
    from rcl_interfaces import srv

    return {"list_parameters": srv.ListParameters, "get_parameters": srv.GetParameters,
            "set_parameters": srv.SetParameters, "describe_parameters": srv.DescribeParameters}[service]


def _list(node, opts) -> int:
    from rcl_interfaces.srv import DescribeParameters, ListParameters

    names = spin_for_discovery(node, opts.spin_time, lambda: node_names(node),
                                   lambda names: all_node_names_known(node, names))
    if opts.node_name:
        target = absolute_node_name(opts.node_name)
        if target not in names and not wait_for_node(node, target, NODE_TIMEOUT_S):
            print("Node not found", file=sys.stderr)
            return 1
        names = [target]
    else:
        names = [n for n in names if not hidden(n)]
    status = 0
    for name in names:
        response = _call(node, name, "list_parameters", ListParameters.Request())
        if response is None:
            status = 1
            continue
        if not opts.node_name:
            print(f"{name}:")
        params = sorted(response.result.names)
        types = {}
        if opts.param_type:
            described = _call(node, name, "describe_parameters", DescribeParameters.Request(names=params))
            types = {d.name: TYPE_NAMES.get(d.type, "unknown") for d in (described.descriptors if described else [])}
        for param in params:
            print(f"  {param} (type: {types.get(param, 'unknown')})" if opts.param_type else f"  {param}")
    return status


def _get(node, target: str, opts) -> int:
    from rcl_interfaces.srv import GetParameters

    response = _call(node, target, "get_parameters", GetParameters.Request(names=[opts.parameter_name]))
    if response is None:
        return 1
    if not response.values:
        print("Parameter not set", file=sys.stderr)
        return 1
    value = response.values[0]
    if value.type == 0:
        print("Parameter not set.")
        return 0
    label, field = TYPE_LABELS[value.type]
    shown = getattr(value, field)
    if hasattr(shown, "tolist"):
        shown = shown.tolist()
    print(shown if opts.hide_type else f"{label} {shown}")
    return 0


def _set(node, target: str, opts) -> int:
    from rcl_interfaces.msg import Parameter
    from rcl_interfaces.srv import SetParameters

    from rclpy.parameter import get_parameter_value as parameter_value  # YAML rules, as ros2cli's

    pairs = list(zip(opts.params_and_values[::2], opts.params_and_values[1::2]))
    request = SetParameters.Request(parameters=[Parameter(name=n, value=parameter_value(v)) for n, v in pairs])
    response = _call(node, target, "set_parameters", request)
    if response is None:
        return 1
    for (name, _), result in zip(pairs, response.results):
        ok = result.successful
        msg = "Set parameter successful" if ok else "Setting parameter failed"
        if result.reason:
            msg += ": " + result.reason
        print(f"{name}: {msg}" if len(pairs) > 1 else msg, file=sys.stdout if ok else sys.stderr)
    return 0


def _describe(node, target: str, opts) -> int:
    from rcl_interfaces.srv import DescribeParameters

    response = _call(node, target, "describe_parameters", DescribeParameters.Request(names=opts.parameter_names))
    if response is None:
        return 1
    for d in response.descriptors:
        print("Parameter name:", d.name)
        print("  Type:", TYPE_NAMES.get(d.type, "unknown"))
        if d.description:
            print("  Description:", d.description)
        print("  Constraints:")
        if d.read_only:
            print("    Read only: true")
        ranges = list(d.floating_point_range) + list(d.integer_range)
        if ranges:
            print("    Min value:", ranges[0].from_value)
            print("    Max value:", ranges[0].to_value)
            if ranges[0].step:
                print("    Step:", ranges[0].step)
        if d.additional_constraints:
            print("    Additional constraints:", d.additional_constraints)
    return 0
