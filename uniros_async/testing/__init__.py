"""Test helpers shipped with the package: the transport contract suite (as trio ships check_one_way_stream)."""
