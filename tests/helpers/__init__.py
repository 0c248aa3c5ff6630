"""Helpers the tests import (``from helpers.cli import ...``): plain functions, no fixtures."""
