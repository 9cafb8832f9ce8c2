//! Wire protocol between the hexcal host and the camera trigger controller (DESIGN.md §12).
#![no_std]
