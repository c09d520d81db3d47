"""Metrology: feature fits, inspection plans, the EF check and accuracy reports."""
