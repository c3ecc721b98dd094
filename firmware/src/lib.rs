//! firmware: the real-time compensator loop (being written).
#![no_std]
