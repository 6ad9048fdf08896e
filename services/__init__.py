"""The federates, one package each (physics, camera, edge, robot, abstract loops), and ``main``,
the process entry point that starts one of them (or netsim) by role. Federates talk only through
messages: none imports another."""
