"""The live prediction node: the middleware-neutral core and its ROS 1 / ROS 2 transports."""
