"""The edge: the only places that start ROS or touch the terminal — the CLI (:mod:`.cli`), the
rclpy nodes (:mod:`.nodes`), the demo (:mod:`.demo`) and the evidence scripts
(:mod:`.evidence`). They use the public API of ``lidarscan`` and ``converters`` only; nothing
below imports them."""
