//! host-sim: simulated piezo plants (being written).
