"""ESC family tests, mirroring bridge/escs/.

A package (as is ``dronecan/`` in it) so that the folder ``tests/escs/dronecan`` is not taken
for the ``dronecan`` package these tests import: mypy and pytest would otherwise find it on
the path they add for the files here.
"""
