"""Clients of robot hardware that need no middleware: ``dxl`` speaks Dynamixel Protocol 2.0 on a serial bus."""
