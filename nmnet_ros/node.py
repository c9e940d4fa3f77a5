"""``python -m nmnet_ros.node``: the node, as the ``nmnet_node`` console script starts it (:mod:`nmnet_ros.ros`)."""

import sys

from nmnet_ros.ros.entry import node_main

if __name__ == "__main__":
    sys.exit(node_main())
