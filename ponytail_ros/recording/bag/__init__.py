"""MCAP bags laid out the way rosbag2's MCAP storage plugin writes them.

A file written by :class:`BagWriter` opens in ``ros2 bag info`` / ``ros2 bag play``, Foxglove and
the ``rosbags`` library like one recorded by ``ros2 bag record -s mcap``:

* header profile ``ros2``;
* one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``, whose data is the
  type's ``.msg`` text followed by every nested non-primitive type (a line of 80 ``=``,
  ``MSG: pkg/Type``, its text), depth first, each dependency once, dependencies of one message in
  sorted order -- what rosbag2_cpp's ``LocalMessageDefinitionSource::get_full_text`` produces;
* one channel per topic, message encoding ``cdr``, with the channel metadata
  ``offered_qos_profiles`` (the YAML rosbag2 writes, metadata version 9 policy names) and
  ``topic_type_hash`` (``RIHS01_...``);
* messages serialised with ``rclpy.serialization`` (padding zeroed, see ``cdr``); ``log_time`` and
  ``publish_time`` in ns;
* a ``rosbag2`` metadata record (``serialized_metadata``: the YAML bag metadata, version 9, plus
  ``ROS_DISTRO``) written when the file is opened and again, with the final counts, when it is
  closed -- as rosbag2's ``SequentialWriter`` does with ``update_metadata`` on open and close;
* uncompressed chunks, like rosbag2's default storage options.

The ``.msg`` texts and type hashes are read from the installed interface packages
(``share/<pkg>/msg/<Type>.msg`` and ``.json``), never from copies in this code.

Time: every time in this module is an integer number of nanoseconds (``*_ns``), on whatever
clock the caller uses for log time (normally the simulation clock).

Durability: file I/O happens on a background thread. The current chunk is pushed to the
operating system when it reaches ``chunk_size`` bytes, when its messages span
``chunk_duration_ns`` of log time, and when no message has arrived for ``chunk_duration_ns`` of
wall time. If the process is killed (SIGKILL, a crash), every chunk pushed before that survives
and :class:`BagReader` reads it back; what is lost is the chunk being built -- messages within
``chunk_duration_ns`` of log time (default 0.5 s) of the end -- plus any messages still queued
for the writer thread (normally none: the thread keeps up unless the disk stalls). Data is not
``fsync``-ed, so this bound covers the death of the process, not of the machine. Such a file has
no summary or index: ``ponytail_replay repair`` rewrites it as a complete, indexed file that
indexed readers (``rosbags``, mcap's ``SeekingReader``) open too.

Reading (:class:`BagReader`) takes what rosbag2 writes: a bag folder (``metadata.yaml`` and
every file it lists, in order: split bags), its ``metadata.yaml``, or one file; MCAP or sqlite3
(``.db3``, read with ``rosbags``) storage; zstd compression of whole files, messages or MCAP
chunks (``layout.py``). It checks every MCAP record (``mcap_scan.py``): a damaged file (chunk or
data-section CRC mismatch, a record that does not fit its length) is an error naming the byte,
never a shorter file; a cut-short one is read up to the cut and says where it is cut.

Signals: :meth:`BagWriter.close` is idempotent and safe to call from a signal handler, a
``finally`` block or ``atexit`` (every writer registers it with ``atexit``, so a normal
interpreter exit finalises the file). SIGTERM's default action kills the process without running
``atexit``; call :meth:`BagWriter.close_on_signals` to finalise on SIGINT/SIGTERM.

The package, split as ``rosbags.rosbag2`` is: ``msgdefs.py`` (message definitions, type
hashes), ``metadata.py`` (QoS YAML, rosbag2's metadata records), ``writer.py``
(:class:`BagWriter`), ``layout.py`` (a path to a bag's files), ``reader.py`` (:class:`BagReader`
and its MCAP file reader), ``db3.py`` (the ``.db3`` file reader), ``wanted.py`` (the topics a
read asks for, checked), ``errors.py``.

It imports rclpy; nothing in ``ponytail_ros.core`` may import it.
"""
from .errors import BagError
from .metadata import PARAMETERS_METADATA
from .msgdefs import message_definition, message_definition_of_text, type_hash
from .reader import BagReader
from .writer import BagWriter

__all__ = ['BagError', 'BagWriter', 'BagReader', 'PARAMETERS_METADATA', 'message_definition',
           'message_definition_of_text', 'type_hash']
