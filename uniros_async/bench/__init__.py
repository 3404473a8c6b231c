"""``uniros bench``: benchmark scenarios. Each module keeps ``main(config)`` apart from argparse."""
