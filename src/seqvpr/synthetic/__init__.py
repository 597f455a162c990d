"""The rendered route world and synthetic route fixtures (the demo and the tests use them)."""
