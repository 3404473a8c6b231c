"""Dynamixel Protocol 2.0 in asyncio: packets (``protocol``), control tables per model (``control_table``) and the
bus client over a serial port's fd (``bus``). docs/dynamixel.md has the facts and their sources.
"""
