"""Drive emulator: servo amplifier, harmonic drive, flexible joint and sensors."""
