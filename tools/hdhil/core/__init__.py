"""The project's base: user errors, typed configuration from plain data, the
data-acquisition board's ADC/DAC conversion that firmware and emulator share, and the
log every fault injector records into."""
