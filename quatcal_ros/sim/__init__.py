"""
Simulated robot cells with known answers.

Stop-and-go streams, noise, outliers (numpy only).
"""
