"""One exception type for bad user input, so the CLI can print one line and exit 2."""


class ConfigError(ValueError):
    """A parameter value outside what is allowed; the message names both."""


def bad_value(name: str, value: object, allowed: str) -> ConfigError:
    """Build the one-line error every entry point uses: parameter, value, what is allowed."""
    return ConfigError(f"invalid {name}={value!r}: {allowed}")
