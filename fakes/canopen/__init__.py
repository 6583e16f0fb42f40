"""Fake CiA 402 drives on a virtual CAN bus (and a socketcand server for another
process), written from the CiA 301/402 documents."""
