"""The rendered route world and synthetic route fixtures (the demo and the tests use them)."""

#: the conditions a drive can be rendered under (here so that reading them costs no renderer import)
CONDITIONS = ("day", "dusk", "night", "winter", "fog", "rain")
