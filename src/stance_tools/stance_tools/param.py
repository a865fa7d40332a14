"""`stance param set NODE NAME VALUE`: change a running node's parameter without the ros2
CLI (which is not on PyPI), e.g. `stance param set /pik_node strategy clamping`.

It calls the node's own parameter services (rcl_interfaces/srv/GetParameterTypes, then
SetParameters), as `ros2 param set` does. VALUE is read as YAML, like `-p name:=value`; a
whole number given for a double parameter is sent as a double. Exit 0 when the node takes
the value, 1 with the node's reason when it refuses it or cannot be reached.
"""

from __future__ import annotations

import argparse
import math
import sys

from .cli import positive


def add_arguments(parser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    set_parser = actions.add_parser("set", help="set one parameter of a running node")
    set_parser.add_argument("node", help="node name, e.g. /pik_node")
    set_parser.add_argument("name", help="parameter name, e.g. strategy")
    set_parser.add_argument("value", help="value, read as YAML (clamping, 0.1, true, [a, b])")
    set_parser.add_argument("--timeout", type=positive(float), default=5.0,
                            help="s to wait for the node's parameter services")


def is_parameter_value(value) -> bool:
    """Whether a ROS parameter can take the value (YAML, as -p and this command read it): a
    boolean, a finite number, a string, or a list of those."""
    if isinstance(value, list):
        return all(is_parameter_value(item) and not isinstance(item, list) for item in value)
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, (bool, int, str))


def run(args) -> int:
    import rclpy
    import yaml
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rclpy.exceptions import InvalidNodeNameException, InvalidServiceNameException
    from rclpy.parameter import get_parameter_value
    from rclpy.parameter_client import AsyncParameterClient

    try:
        parsed = yaml.safe_load(args.value)
    except yaml.YAMLError:
        parsed = args.value         # get_parameter_value takes it as a string too
    if not is_parameter_value(parsed):
        print(f"stance param: {args.value!r} is not a parameter value (a boolean, number, "
              "string or list of one of these)", file=sys.stderr)
        return 2
    rclpy.init()
    node = rclpy.create_node("stance_param")
    try:
        try:
            client = AsyncParameterClient(node, args.node)
        except (InvalidNodeNameException, InvalidServiceNameException) as error:
            print(f"stance param: {args.node!r} is not a node name: "
                  f"{str(error).splitlines()[0].rstrip(':')}", file=sys.stderr)
            return 2

        def answer(future):
            rclpy.spin_until_future_complete(node, future, timeout_sec=args.timeout)
            if not future.done():
                raise TimeoutError(f"{args.node} did not answer within {args.timeout:g} s")
            return future.result()

        if not client.wait_for_services(timeout_sec=args.timeout):
            raise TimeoutError(f"no parameter services of {args.node} within "
                               f"{args.timeout:g} s (is the node running?)")
        # an undeclared name: no type at all (rclpy) or NOT_SET
        declared = [*answer(client.get_parameter_types([args.name])).types,
                    ParameterType.PARAMETER_NOT_SET][0]
        if declared == ParameterType.PARAMETER_NOT_SET:
            print(f"stance param: {args.node} has no parameter {args.name!r}", file=sys.stderr)
            return 1
        value = get_parameter_value(args.value)
        if declared == ParameterType.PARAMETER_DOUBLE \
                and value.type == ParameterType.PARAMETER_INTEGER:
            value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                   double_value=float(value.integer_value))
        [result] = answer(client.set_parameters([Parameter(name=args.name,
                                                           value=value)])).results
        if not result.successful:
            print(f"stance param: {args.node} refused {args.name} = {args.value}: "
                  f"{result.reason}", file=sys.stderr)
            return 1
        print(f"{args.node}: {args.name} = {args.value}")
        return 0
    except TimeoutError as error:
        print(f"stance param: {error}", file=sys.stderr)
        return 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
