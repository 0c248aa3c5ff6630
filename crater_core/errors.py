"""Errors raised for bad data at the renderer/training contract."""


class ContractError(ValueError):
    """Bad input at the contract: a malformed manifest row, a nonsense sweep value, a bad checksum."""
