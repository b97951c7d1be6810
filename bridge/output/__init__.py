"""The output side: from the mixed input to CAN frames at a fixed rate, safely."""
