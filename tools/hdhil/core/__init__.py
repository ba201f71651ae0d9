"""The project's base: user errors, typed configuration from plain data, and the
data-acquisition board's ADC/DAC conversion that firmware and emulator share."""
